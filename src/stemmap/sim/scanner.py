"""2D laser scanner simulation by exact ray casting against a :class:`~stemmap.sim.forest.Stand`.

Two ray casters give the same first-hit distances:

* :func:`cast_rays` -- arbitrary ray directions from one origin, plain numpy, (B x objects)
  brute force. The reference implementation (used by the tests to check the fast one).
* :func:`cast_scans` -- many scans of one uniform beam fan from many poses. Every object is
  "rasterised" into the few beams its angular extent covers (a numba kernel), so the cost is
  O(scans x objects in range x beams per object), not O(scans x beams x objects).

:func:`simulate_scans` adds the sensor model on top: beam divergence sampled by sub-beams
(mixed pixels at trunk edges), range noise (absolute + proportional to range), dropouts,
range window. Ground truth per beam is the id of the object that the beam footprint hits
(tree index, ``-2`` clutter, ``-1`` nothing).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.errors import ConfigError, InputError
from stemmap.sim.footprint import beam_range, sub_ray_offsets
from stemmap.sim.forest import Stand
from stemmap.types import FloatArray, LaserScan, Pose2, ScanBatch

__all__ = [
    "HIT_CLUTTER",
    "HIT_NONE",
    "SCANNER_PRESETS",
    "ScannerModel",
    "cast_rays",
    "cast_scans",
    "scanner_preset",
    "simulate_scan",
    "simulate_scans",
]

#: ``hit_id`` of a beam that hit clutter (bush, rock, wall, branch).
HIT_CLUTTER = -2
#: ``hit_id`` of a beam that hit nothing within ``range_max``.
HIT_NONE = -1


@dataclass(frozen=True)
class ScannerModel:
    """Geometry and noise of a 2D scanner.

    Parameters
    ----------
    angle_min, angle_max : float, radians
        Inclusive span of beam centres, counter-clockwise from the sensor's x axis.
    angle_increment : float, radians, > 0
    range_min, range_max : float, metres
        Returns outside (range_min, range_max) are reported as "no return" (``inf``).
    range_noise : float, metres, >= 0
        Constant part of the 1-sigma Gaussian range noise.
    dropout : float in [0, 1)
        Probability that a beam which hit something returns nothing.
    range_noise_rel : float, >= 0
        Range-proportional part of the noise: ``sigma(r) = range_noise + range_noise_rel * r``
        (triangulation scanners such as RPLIDAR are specified as a percentage of range).
    beam_divergence : float, radians, >= 0
        Full angular width of the beam footprint. ``0`` is an ideal thin ray.
    sub_beams : int, >= 1
        Thin rays sampling the footprint when ``beam_divergence > 0``: the centres of
        ``sub_beams`` equal cells tiling it (:func:`stemmap.sim.footprint.sub_ray_offsets`).
        Default 25 (5 before Dec 5): the outermost sub-beams sit ``divergence / (2 K)``
        inside the footprint's edges, which widens the gap between neighbouring footprints by
        ``divergence / K``: 0.02 beam steps for the SICK preset (0.1 with 5), and the covered
        share moves in steps of 1/K (the detector's mixed-pixel prior has a std of 0.2).
    min_hit_fraction : float in (0, 1]
        Fraction of the footprint that must hit a surface for the beam to return (an energy
        threshold). 0.5 keeps silhouette edges unbiased on average; the ``sick_lms`` preset
        uses 0.3, the threshold measured on a real SICK LMS200 (Victoria Park).
    scan_rate_hz : float, > 0
        Scans per second (used as the default rate of :func:`~stemmap.sim.trajectory.simulate_run`).

    Notes
    -----
    **Mixed pixels.** When the footprint straddles a trunk edge, part of the sub-beams hit
    the trunk and part the background. The returned range is the mean of the sub-beams that
    hit, weighted by ``1 / r^2`` (returned energy of a diffuse target; the model, its sources
    and what it leaves out: :mod:`stemmap.sim.footprint`, shared with the real-geometry
    benchmark); it therefore lies between the two ranges, as the "mixed pixels" (phantom
    points) that real time-of-flight scanners report at edges. Ground truth of such a beam is
    the object that covers most sub-beams (ties: the nearest).
    """

    angle_min: float = -math.pi / 2
    angle_max: float = math.pi / 2
    angle_increment: float = math.radians(0.5)
    range_min: float = 0.05
    range_max: float = 30.0
    range_noise: float = 0.01
    dropout: float = 0.0
    range_noise_rel: float = 0.0
    beam_divergence: float = 0.0
    sub_beams: int = 25
    min_hit_fraction: float = 0.5
    scan_rate_hz: float = 10.0

    def __post_init__(self) -> None:
        if not self.angle_increment > 0:
            raise ConfigError(f"angle_increment must be > 0 rad, got {self.angle_increment}.")
        if not self.angle_max > self.angle_min:
            raise ConfigError(
                f"angle_max ({self.angle_max}) must exceed angle_min ({self.angle_min})."
            )
        if not 0.0 <= self.dropout < 1.0:
            raise ConfigError(f"dropout must be in [0, 1), got {self.dropout}.")
        if not (0.0 <= self.range_min < self.range_max):
            raise ConfigError(
                f"range window must satisfy 0 <= range_min < range_max, got "
                f"[{self.range_min}, {self.range_max}]."
            )
        for name in ("range_noise", "range_noise_rel", "beam_divergence"):
            v = getattr(self, name)
            if not (v >= 0.0 and math.isfinite(v)):
                raise ConfigError(f"{name} must be finite and >= 0, got {v}.")
        if int(self.sub_beams) != self.sub_beams or self.sub_beams < 1:
            raise ConfigError(f"sub_beams must be an integer >= 1, got {self.sub_beams}.")
        if not 0.0 < self.min_hit_fraction <= 1.0:
            raise ConfigError(f"min_hit_fraction must be in (0, 1], got {self.min_hit_fraction}.")
        if not self.scan_rate_hz > 0:
            raise ConfigError(f"scan_rate_hz must be > 0, got {self.scan_rate_hz}.")

    @property
    def n_beams(self) -> int:
        return round((self.angle_max - self.angle_min) / self.angle_increment) + 1

    @property
    def angles(self) -> FloatArray:
        return self.angle_min + self.angle_increment * np.arange(self.n_beams, dtype=np.float64)

    @property
    def sub_beam_offsets(self) -> FloatArray:
        """Angular offsets (rad) of the sub-beams from the beam centre, shape (K,)."""
        k = int(self.sub_beams) if self.beam_divergence > 0 else 1
        return sub_ray_offsets(self.beam_divergence, k)

    def range_sigma(self, ranges: ArrayLike) -> FloatArray:
        """1-sigma range noise (m) at the given true ranges."""
        return self.range_noise + self.range_noise_rel * np.asarray(ranges, dtype=np.float64)


#: Published-spec-like scanner presets. ``sick_lms``: SICK LMS2xx, 0.5 deg, 180 deg FOV, 80 m,
#: ~1 cm noise, ~0.25 deg divergence, 75 Hz, returns when 0.3 of the footprint hits (the real
#: LMS200 of Victoria Park, q ~ 0.25-0.38 at 2-15 m, benchmarks/vp_return_threshold.py; 0.5
#: before Dec 6: docs/algorithms/scan-detection.md "One return threshold for the simulator and
#: the benchmark"). ``rplidar``: RPLIDAR-like, 1 deg, 360 deg, 12 m, 1.5 % of range noise,
#: 10 Hz (divergence and dropout are our assumptions; see docs/algorithms/sim-eval.md).
SCANNER_PRESETS: dict[str, ScannerModel] = {
    "sick_lms": ScannerModel(
        angle_min=-math.pi / 2,
        angle_max=math.pi / 2,
        angle_increment=math.radians(0.5),
        range_min=0.05,
        range_max=80.0,
        range_noise=0.01,
        range_noise_rel=0.0,
        beam_divergence=math.radians(0.25),
        sub_beams=25,
        min_hit_fraction=0.3,
        dropout=0.0,
        scan_rate_hz=75.0,
    ),
    "rplidar": ScannerModel(
        angle_min=-math.pi,
        angle_max=math.pi - math.radians(1.0),
        angle_increment=math.radians(1.0),
        range_min=0.15,
        range_max=12.0,
        range_noise=0.0,
        range_noise_rel=0.015,
        beam_divergence=math.radians(0.5),
        sub_beams=5,
        dropout=0.01,
        scan_rate_hz=10.0,
    ),
}


def scanner_preset(scanner: ScannerModel | str | None, **overrides: float) -> ScannerModel:
    """A :class:`ScannerModel` from a model, a preset name or ``None`` (default model).

    Keyword overrides replace fields (e.g. ``range_noise=0.02``).

    Raises
    ------
    ConfigError
        If the preset name is unknown or an override is not a field.
    """
    if scanner is None:
        model = ScannerModel()
    elif isinstance(scanner, ScannerModel):
        model = scanner
    elif isinstance(scanner, str):
        try:
            model = SCANNER_PRESETS[scanner]
        except KeyError as exc:
            raise ConfigError(
                f"unknown scanner preset {scanner!r}; choose one of {sorted(SCANNER_PRESETS)}."
            ) from exc
    else:
        raise ConfigError(f"scanner must be a ScannerModel or preset name, got {scanner!r}.")
    if overrides:
        try:
            model = replace(model, **overrides)  # type: ignore[arg-type]
        except TypeError as exc:
            raise ConfigError(f"bad scanner override: {exc}.") from exc
    return model


# --------------------------------------------------------------------------------------------
# Reference ray caster (numpy, arbitrary directions)
# --------------------------------------------------------------------------------------------


def _circles(stand: Stand) -> tuple[FloatArray, FloatArray, NDArray[np.int64]]:
    """Circles that reflect: round trees (not the polygonal ones) and clutter circles."""
    round_trees = ~stand.tree_is_polygon
    centers = np.vstack((stand.trees_xy[round_trees], stand.clutter_xy))
    radii = np.concatenate((stand.radii[round_trees], stand.clutter_radius))
    ids = np.concatenate(
        (
            np.flatnonzero(round_trees).astype(np.int64),
            np.full(len(stand.clutter_radius), HIT_CLUTTER, dtype=np.int64),
        )
    )
    return centers, radii, ids


def cast_rays(
    origin: ArrayLike, directions: ArrayLike, stand: Stand, max_range: float
) -> tuple[FloatArray, NDArray[np.int64]]:
    """Exact first-hit distances of rays from one origin against the stand's circles and segments.

    Parameters
    ----------
    origin : array_like of shape (2,), metres, world frame
    directions : array_like of shape (B,), radians, world frame
    stand : Stand
    max_range : float, metres

    Returns
    -------
    ranges : ndarray of shape (B,)
        Distance to the first hit, ``inf`` where nothing is hit within ``max_range``.
    hit_id : ndarray of shape (B,), int
        Tree index for trees (and polygon segments owned by a tree), ``-2`` for clutter,
        ``-1`` for no hit.
    """
    o = np.asarray(origin, dtype=np.float64).reshape(2)
    dirs = np.asarray(directions, dtype=np.float64).reshape(-1)
    u = np.column_stack((np.cos(dirs), np.sin(dirs)))  # (B, 2)
    n_b = u.shape[0]
    best = np.full(n_b, np.inf)
    hit = np.full(n_b, HIT_NONE, dtype=np.int64)

    centers, radii, ids = _circles(stand)
    if centers.shape[0]:
        rel = centers - o  # (C, 2)
        dist = np.hypot(rel[:, 0], rel[:, 1])
        keep = dist - radii < max_range
        rel, radii_k, ids_k = rel[keep], radii[keep], ids[keep]
        if rel.shape[0]:
            # |t u - c|^2 = r^2  ->  t = b - sqrt(b^2 - (|c|^2 - r^2)), b = u.c
            b = u @ rel.T  # (B, C)
            cc = np.sum(rel * rel, axis=1) - radii_k**2  # (C,)
            disc = b * b - cc
            with np.errstate(invalid="ignore"):
                t = b - np.sqrt(disc)
            t = np.where((disc >= 0) & (t > 0), t, np.inf)
            j = np.argmin(t, axis=1)
            tj = t[np.arange(n_b), j]
            better = tj < best
            best = np.where(better, tj, best)
            hit = np.where(better, ids_k[j], hit)

    if stand.segments.shape[0]:
        seg = stand.segments
        p0 = seg[:, :2] - o
        d = seg[:, 2:] - seg[:, :2]  # (S, 2)
        # Solve t u = p0 + s d  ->  cross products
        den = u[:, :1] * d[:, 1] - u[:, 1:] * d[:, 0]  # (B, S)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (p0[:, 0] * d[:, 1] - p0[:, 1] * d[:, 0]) / den
            s = (p0[:, 0] * u[:, 1:] - p0[:, 1] * u[:, :1]) / den
        valid = (np.abs(den) > 1e-12) & (t > 0) & (s >= 0) & (s <= 1)
        t = np.where(valid, t, np.inf)
        j = np.argmin(t, axis=1)
        tj = t[np.arange(n_b), j]
        owner = np.where(stand.segment_owner >= 0, stand.segment_owner, HIT_CLUTTER)
        better = tj < best
        best = np.where(better, tj, best)
        hit = np.where(better, owner[j], hit)

    far = best >= max_range
    best[far] = np.inf
    hit[far] = HIT_NONE
    return best, hit


# --------------------------------------------------------------------------------------------
# Fast batch caster (numba): rasterise each object into the beams it covers
# --------------------------------------------------------------------------------------------


@numba.njit(cache=True)
def _beam_index_range(
    psi_lo: float, psi_hi: float, inc: float, n_beams: int
) -> tuple[int, int, int, int]:
    """Beam index intervals [a0, b0], [a1, b1] covering relative angles [psi_lo, psi_hi].

    Angles are relative to beam 0 (radians); the interval is tried at shifts of -2pi, 0 and
    +2pi so that objects across a 360-degree scanner's seam are found. For spans < 2pi at most
    two shifted intervals are non-empty; an empty interval has a > b.
    """
    two_pi = 2.0 * math.pi
    i0a, i0b, i1a, i1b = 1, 0, 1, 0
    found = 0
    for k in range(3):
        shift = (k - 1) * two_pi
        a = max(math.ceil((psi_lo + shift) / inc), 0)
        b = min(math.floor((psi_hi + shift) / inc), n_beams - 1)
        if a <= b:
            if found == 0:
                i0a, i0b = a, b
            else:
                i1a, i1b = a, b
            found += 1
    return i0a, i0b, i1a, i1b


@numba.njit(cache=True)
def _cast_scans_kernel(
    poses: FloatArray,
    angle0: float,
    offsets: FloatArray,
    inc: float,
    n_beams: int,
    circles: FloatArray,
    circle_ids: NDArray[np.int64],
    segments: FloatArray,
    segment_ids: NDArray[np.int64],
    max_range: float,
    out_r: FloatArray,
    out_id: NDArray[np.int64],
) -> None:
    """First hits of ray ``(s, i, k)`` at world angle ``theta_s + angle0 + offsets[k] + i inc``.

    Each object's bearing and angular half-width are computed once per scan and reused for
    every sub-beam offset (that per-object work dominates the cost).
    """
    n_scans = poses.shape[0]
    n_c = circles.shape[0]
    n_s = segments.shape[0]
    n_k = offsets.shape[0]
    two_pi = 2.0 * math.pi
    for s in range(n_scans):
        ox = poses[s, 0]
        oy = poses[s, 1]
        base = poses[s, 2] + angle0  # world angle of beam 0 (before the offsets)
        for i in range(n_beams):
            for k in range(n_k):
                out_r[s, i, k] = np.inf
                out_id[s, i, k] = -1
        for c in range(n_c):
            cx = circles[c, 0] - ox
            cy = circles[c, 1] - oy
            r = circles[c, 2]
            d2 = cx * cx + cy * cy
            d = math.sqrt(d2)
            if d - r >= max_range or d <= r:
                continue
            half = math.asin(r / d)
            psi = math.atan2(cy, cx) - base
            psi = psi - two_pi * math.floor(psi / two_pi)  # [0, 2pi)
            cc = d2 - r * r
            for k in range(n_k):
                off = offsets[k]
                a0, b0, a1, b1 = _beam_index_range(psi - off - half, psi - off + half, inc, n_beams)
                for rng_a, rng_b in ((a0, b0), (a1, b1)):
                    for i in range(rng_a, rng_b + 1):
                        ang = base + off + inc * i
                        ux = math.cos(ang)
                        uy = math.sin(ang)
                        b = ux * cx + uy * cy
                        disc = b * b - cc
                        if disc < 0.0:
                            continue
                        t = b - math.sqrt(disc)
                        if 0.0 < t < out_r[s, i, k]:
                            out_r[s, i, k] = t
                            out_id[s, i, k] = circle_ids[c]
        for g in range(n_s):
            p0x = segments[g, 0] - ox
            p0y = segments[g, 1] - oy
            p1x = segments[g, 2] - ox
            p1y = segments[g, 3] - oy
            dx = p1x - p0x
            dy = p1y - p0y
            # distance from the origin to the segment (cull)
            L2 = dx * dx + dy * dy
            if L2 > 0.0:
                tt = -(p0x * dx + p0y * dy) / L2
                tt = min(1.0, max(0.0, tt))
            else:
                tt = 0.0
            qx = p0x + tt * dx
            qy = p0y + tt * dy
            if math.sqrt(qx * qx + qy * qy) >= max_range:
                continue
            phi0 = math.atan2(p0y, p0x) - base
            phi0 = phi0 - two_pi * math.floor(phi0 / two_pi)
            span = math.atan2(p0x * p1y - p0y * p1x, p0x * p1x + p0y * p1y)  # (-pi, pi]
            lo = phi0 + min(0.0, span)
            hi = phi0 + max(0.0, span)
            for k in range(n_k):
                off = offsets[k]
                a0, b0, a1, b1 = _beam_index_range(lo - off - 1e-12, hi - off + 1e-12, inc, n_beams)
                for rng_a, rng_b in ((a0, b0), (a1, b1)):
                    for i in range(rng_a, rng_b + 1):
                        ang = base + off + inc * i
                        ux = math.cos(ang)
                        uy = math.sin(ang)
                        den = ux * dy - uy * dx
                        if abs(den) <= 1e-12:
                            continue
                        t = (p0x * dy - p0y * dx) / den
                        sp = (p0x * uy - p0y * ux) / den
                        if t > 0.0 and 0.0 <= sp <= 1.0 and t < out_r[s, i, k]:
                            out_r[s, i, k] = t
                            out_id[s, i, k] = segment_ids[g]
        for i in range(n_beams):
            for k in range(n_k):
                if out_r[s, i, k] >= max_range:
                    out_r[s, i, k] = np.inf
                    out_id[s, i, k] = -1


def _cast_sub_beams(
    stand: Stand,
    poses: FloatArray,
    angle_min: float,
    offsets: FloatArray,
    angle_increment: float,
    n_beams: int,
    max_range: float,
) -> tuple[FloatArray, NDArray[np.int64]]:
    """(S, N, K) first-hit ranges and ids of every sub-beam (see :func:`cast_scans`)."""
    p = np.ascontiguousarray(np.asarray(poses, dtype=np.float64).reshape(-1, 3))
    if not np.all(np.isfinite(p)):
        raise InputError("cast_scans: every sensor pose must be finite.")
    if not angle_increment > 0:
        raise InputError(f"cast_scans needs angle_increment > 0, got {angle_increment}.")
    centers, radii, ids = _circles(stand)
    circles = np.ascontiguousarray(np.column_stack((centers, radii)).reshape(-1, 3))
    seg = np.ascontiguousarray(stand.segments.reshape(-1, 4))
    seg_ids = np.where(stand.segment_owner >= 0, stand.segment_owner, HIT_CLUTTER).astype(np.int64)
    off = np.ascontiguousarray(np.asarray(offsets, dtype=np.float64).reshape(-1))
    out_r = np.empty((p.shape[0], int(n_beams), off.size))
    out_id = np.empty((p.shape[0], int(n_beams), off.size), dtype=np.int64)
    _cast_scans_kernel(
        p,
        float(angle_min),
        off,
        float(angle_increment),
        int(n_beams),
        circles,
        np.ascontiguousarray(ids),
        seg,
        np.ascontiguousarray(seg_ids),
        float(max_range),
        out_r,
        out_id,
    )
    return out_r, out_id


def cast_scans(
    stand: Stand,
    poses: ArrayLike,
    *,
    angle_min: float,
    angle_increment: float,
    n_beams: int,
    max_range: float,
) -> tuple[FloatArray, NDArray[np.int64]]:
    """Exact first-hit ranges of a uniform beam fan from many sensor poses.

    Parameters
    ----------
    stand : Stand
    poses : array_like of shape (S, 3)
        Sensor poses (x, y in metres, theta in radians) in the world frame.
    angle_min, angle_increment : float, radians
        Beam ``i`` points at ``theta + angle_min + i * angle_increment``; ``angle_increment > 0``.
    n_beams : int
    max_range : float, metres

    Returns
    -------
    ranges : ndarray of shape (S, n_beams), ``inf`` = nothing within ``max_range``
    hit_id : ndarray of shape (S, n_beams), int (tree index, -2 clutter, -1 nothing)

    Notes
    -----
    Same geometry as :func:`cast_rays`: the ray ``o + t u`` meets the circle ``|p - c| = r`` at
    ``t = u.c' - sqrt((u.c')^2 - |c'|^2 + r^2)`` with ``c' = c - o``; the segment
    ``p0 + s d`` at ``t = (p0 x d) / (u x d)``. Only the beams inside each object's angular
    extent (``asin(r/|c'|)`` around the bearing for circles) are tested.
    """
    r, h = _cast_sub_beams(
        stand,
        np.asarray(poses, dtype=np.float64),
        angle_min,
        np.zeros(1),
        angle_increment,
        n_beams,
        max_range,
    )
    return r[..., 0], h[..., 0]


# --------------------------------------------------------------------------------------------
# Sensor model
# --------------------------------------------------------------------------------------------


@numba.njit(cache=True)
def _combine_kernel(
    sub_r: FloatArray,
    sub_id: NDArray[np.int64],
    weight: FloatArray,
    min_share: float,
    out_r: FloatArray,
    out_id: NDArray[np.int64],
    out_mixed: NDArray[np.bool_],
) -> None:
    n_s, n_b, k = sub_r.shape
    for s in range(n_s):
        for i in range(n_b):
            r_b = beam_range(sub_r[s, i], weight, min_share)
            if not r_b < np.inf:
                out_r[s, i] = np.inf
                out_id[s, i] = -1
                out_mixed[s, i] = False
                continue
            out_r[s, i] = r_b
            best_id = -1
            best_count = 0
            best_range = np.inf
            mixed = False
            for j in range(k):
                if sub_id[s, i, j] != sub_id[s, i, 0]:
                    mixed = True
                r = sub_r[s, i, j]
                if not r < np.inf:
                    continue
                count = 0
                for q in range(k):
                    if sub_id[s, i, q] == sub_id[s, i, j] and sub_r[s, i, q] < np.inf:
                        count += 1
                if count > best_count or (count == best_count and r < best_range):
                    best_count = count
                    best_id = sub_id[s, i, j]
                    best_range = r
            out_id[s, i] = best_id
            out_mixed[s, i] = mixed


def _combine_sub_beams(
    sub_r: FloatArray, sub_id: NDArray[np.int64], min_hit_fraction: float
) -> tuple[FloatArray, NDArray[np.int64], NDArray[np.bool_]]:
    """Mixed-pixel model: (S, N, K) sub-beam ranges -> (S, N) range, hit id, mixed flag.

    Range: :func:`stemmap.sim.footprint.beam_range` (the ``1/r^2``-weighted mean of the
    sub-beams that hit, each carrying ``1/K`` of the beam's power, if at least
    ``min_hit_fraction`` of them hit, else no return; the model the real-geometry benchmark's
    virtual scanner uses too). Ground truth: the id covering most sub-beams (ties: the one
    with the nearest sub-beam). Mixed: the sub-beams disagree.
    """
    k = sub_r.shape[-1]
    if k == 1:
        return sub_r[..., 0], sub_id[..., 0], np.zeros(sub_r.shape[:-1], dtype=bool)
    out_r = np.empty(sub_r.shape[:-1])
    out_id = np.empty(sub_r.shape[:-1], dtype=np.int64)
    out_mixed = np.empty(sub_r.shape[:-1], dtype=bool)
    _combine_kernel(
        np.ascontiguousarray(sub_r),
        np.ascontiguousarray(sub_id),
        np.ones(k),
        float(min_hit_fraction),
        out_r,
        out_id,
        out_mixed,
    )
    return out_r, out_id, out_mixed


#: Sub-beam samples (scans x beams x sub-beams) processed per chunk in :func:`simulate_scans`.
_SUB_BEAM_CHUNK = 1 << 17


def simulate_scans(
    stand: Stand,
    poses: ArrayLike,
    model: ScannerModel | str | None = None,
    *,
    times: ArrayLike | None = None,
    rng: np.random.Generator | int | None = None,
    frame: str = "laser",
) -> tuple[ScanBatch, NDArray[np.int64], NDArray[np.bool_]]:
    """Simulate scans from many sensor poses (vectorised; thousands of scans per second).

    Parameters
    ----------
    stand : Stand
    poses : array_like of shape (S, 3)
        Sensor poses (x, y, theta) in the world frame.
    model : ScannerModel or preset name (see :data:`SCANNER_PRESETS`), optional
    times : array_like of shape (S,), seconds, optional
        Scan times; default ``arange(S) / model.scan_rate_hz``.
    rng : numpy Generator or int seed
    frame : str
        Name of the sensor frame of the returned scans.

    Returns
    -------
    scans : ScanBatch
        Ranges in the sensor frame; "no return" is ``inf``.
    hit_ids : ndarray of shape (S, N), int
        Ground truth per beam: tree index, ``-2`` clutter, ``-1`` nothing (also for dropouts
        and returns outside the range window).
    mixed : ndarray of shape (S, N), bool
        Beams whose footprint hit more than one object or an object and the background.

    Notes
    -----
    Per beam: cast ``sub_beams`` exact rays across the divergence, combine them with the mixed
    pixel model (:class:`ScannerModel` Notes), add ``N(0, sigma(r)^2)`` range noise with
    ``sigma(r) = range_noise + range_noise_rel * r``, drop with probability ``dropout``, then
    apply the range window.

    Examples
    --------
    >>> from stemmap.sim import Stand
    >>> stand = Stand([[5.0, 0.0]], [0.4])  # one 40 cm trunk 5 m ahead
    >>> scans, hit, mixed = simulate_scans(stand, [[0.0, 0.0, 0.0]], "sick_lms", rng=0)
    >>> scans.ranges.shape, int((hit == 0).sum())
    ((1, 361), 9)
    >>> bool(abs(np.min(scans.ranges) - 4.8) < 0.05)  # front of the trunk, 1 cm noise
    True
    """
    m = scanner_preset(model)
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    n_s = p.shape[0]
    if times is None:
        t = np.arange(n_s, dtype=np.float64) / m.scan_rate_hz
    else:
        t = np.asarray(times, dtype=np.float64).reshape(-1)
        if t.shape[0] != n_s:
            raise InputError(f"simulate_scans got {n_s} poses but {t.shape[0]} times.")
    gen = np.random.default_rng(rng)
    offsets = m.sub_beam_offsets
    n_b = m.n_beams
    ranges = np.empty((n_s, n_b))
    hit = np.empty((n_s, n_b), dtype=np.int64)
    mixed = np.empty((n_s, n_b), dtype=bool)
    # chunks of scans keep the (chunk, N, K) sub-beam buffers in cache
    chunk = max(1, _SUB_BEAM_CHUNK // max(1, n_b * offsets.size))
    for c0 in range(0, n_s, chunk):
        pc = p[c0 : c0 + chunk]
        sub_r, sub_id = _cast_sub_beams(
            stand, pc, m.angle_min, offsets, m.angle_increment, n_b, m.range_max
        )
        sl = slice(c0, c0 + pc.shape[0])
        ranges[sl], hit[sl], mixed[sl] = _combine_sub_beams(sub_r, sub_id, m.min_hit_fraction)
    finite = np.isfinite(ranges)
    sigma = m.range_sigma(np.where(finite, ranges, 0.0))
    noise = gen.standard_normal(ranges.shape) * sigma
    ranges = np.where(finite, ranges + noise, np.inf)
    if m.dropout > 0:
        drop = gen.random(ranges.shape) < m.dropout
        ranges[drop] = np.inf
    with np.errstate(invalid="ignore"):
        outside = ~((ranges > m.range_min) & (ranges < m.range_max))
    ranges[outside] = np.inf
    hit = np.where(outside, HIT_NONE, hit)
    mixed &= ~outside
    batch = ScanBatch(ranges, t, m.angle_min, m.angle_increment, m.range_min, m.range_max, frame)
    return batch, hit, mixed


def simulate_scan(
    stand: Stand,
    pose: Pose2,
    model: ScannerModel | str | None = None,
    *,
    time: float = 0.0,
    rng: np.random.Generator | int | None = None,
) -> tuple[LaserScan, NDArray[np.int64]]:
    """Simulate one scan from ``pose`` (sensor pose in the world frame).

    Returns the scan (in the sensor frame, "no return" as ``inf``) and the per-beam hit id
    (tree index, -2 clutter, -1 nothing). See :func:`simulate_scans` for the sensor model.
    """
    batch, hit, _ = simulate_scans(
        stand, [[pose.x, pose.y, pose.theta]], model, times=[time], rng=rng
    )
    return batch[0], hit[0]
