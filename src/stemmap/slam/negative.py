"""False-tree removal with negative information (Öhman et al. 2007, §2.2 and Fig. 5).

Öhman's Forestrix SLAM optimistically accepts every echo as a tree; a second algorithm removes
false trees afterwards: scans are projected into the map and intersected with the mapped trees;
"if there are more rays passing through a tree than there are valid measurements of that tree,
the tree is removed from the map".

We work on tree detections (range, bearing per frame), not raw rays, so a "ray passing through a
tree" becomes "a frame in which the tree should have been seen but was not": the tree is inside
the sensor's field of view and range window and not occluded by a nearer mapped tree (ray-cast
against the mapped trees drawn with their diameters), yet no detection of that frame lies within
``gate`` of it. A tree is removed when such misses outnumber its hits (Öhman's rule) -- or, with
``rule="log_odds"`` (ours), when its log-odds belief under a detection probability ``p_detect``
and a false-alarm probability ``p_false`` falls below zero.

Works as a post-step for every back-end: :func:`remove_false_trees` takes a
:class:`~stemmap.types.StemMap`, vehicle poses at the frame times and the frames themselves.

:func:`ray_pass_through` is Öhman's Fig. 5 as drawn: the *raw* scans are projected into the map
and every beam is intersected with every mapped tree (a disc of its diameter). A beam crossing
the tree's core that returns from the tree is a valid measurement of it; one that returns
``pass_margin`` or more behind the tree's far side (or not at all, inside the scanner's range)
passed *through* it; one stopped well before the tree was occluded. The same two rules decide
(misses = pass-through beams); :func:`remove_false_trees_by_rays` applies it to a stem map.

References
----------
.. [Ohman2007] M. Öhman et al., "Tree Measurement and Simultaneous Localization and Mapping
   System for Forest Harvesters", FSR 2007, §2.2, Fig. 5.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.errors import ConfigError, InputError
from stemmap.types import FloatArray, ScanBatch, StemMap, wrap_angle

if TYPE_CHECKING:  # pragma: no cover
    from stemmap.slam.base import SlamProblem, SlamResult

Rule = Literal["ohman2007", "log_odds"]

__all__ = [
    "NegativeInfoResult",
    "SensorFov",
    "expected_visibility",
    "negative_information",
    "ray_pass_through",
    "remove_false_trees",
    "remove_false_trees_after",
    "remove_false_trees_by_rays",
]


@dataclass(frozen=True)
class SensorFov:
    """Field of view and range window of the tree detector.

    Parameters
    ----------
    bearing_min, bearing_max : float, rad
        Bearings (CCW from the sensor's forward axis) the sensor covers.
    range_min, range_max : float, m
        Range window in which a tree is expected to be *detected* (usually shorter than the laser's
        maximum range: small trunks far away are rarely detected).
    """

    bearing_min: float = -math.pi / 2
    bearing_max: float = math.pi / 2
    range_min: float = 1.0
    range_max: float = 20.0

    def __post_init__(self) -> None:
        if not self.bearing_max > self.bearing_min:
            raise ConfigError(
                f"SensorFov: bearing_max ({self.bearing_max}) must exceed bearing_min "
                f"({self.bearing_min})."
            )
        if not (0.0 <= self.range_min < self.range_max):
            raise ConfigError(
                f"SensorFov: need 0 <= range_min < range_max, got [{self.range_min}, "
                f"{self.range_max}] m."
            )


@dataclass(frozen=True, eq=False)
class NegativeInfoResult:
    """Per-tree evidence from :func:`negative_information`.

    Attributes
    ----------
    hits : ndarray (N,), int -- frames in which the tree was expected and detected
    misses : ndarray (N,), int -- frames in which it was expected but not detected
    occluded : ndarray (N,), int -- frames in which it was in view but hidden by a nearer tree
    log_odds : ndarray (N,), float -- belief (only meaningful for ``rule="log_odds"``)
    keep : ndarray (N,), bool
    """

    hits: NDArray[np.int64]
    misses: NDArray[np.int64]
    occluded: NDArray[np.int64]
    log_odds: FloatArray
    keep: NDArray[np.bool_]

    @property
    def n_removed(self) -> int:
        return int(np.count_nonzero(~self.keep))


def expected_visibility(
    trees_xy: ArrayLike,
    radii: ArrayLike,
    sensor_pose: ArrayLike,
    fov: SensorFov,
    *,
    occlusion_fraction: float = 0.5,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Which mapped trees a sensor at ``sensor_pose`` should see (one frame).

    A tree is *in view* when its centre lies inside the bearing and range window; it is
    *occluded* when at least ``occlusion_fraction`` of its angular extent is covered by the
    angular extents of nearer trees (each trunk a disc of its radius, ray-cast from the sensor).

    Parameters
    ----------
    trees_xy : ndarray (N, 2), m, map frame
    radii : ndarray (N,), m (NaN is treated as 0.1 m)
    sensor_pose : (3,) sensor x, y, heading in the map frame
    fov : SensorFov
    occlusion_fraction : float in (0, 1]

    Returns
    -------
    in_view, occluded : ndarray (N,) of bool (``occluded`` implies ``in_view``)
    """
    xy = np.asarray(trees_xy, dtype=np.float64).reshape(-1, 2)
    r = np.asarray(radii, dtype=np.float64).reshape(-1)
    r = np.where(np.isfinite(r) & (r > 0), r, 0.1)
    sp = np.asarray(sensor_pose, dtype=np.float64).reshape(3)
    rel = xy - sp[:2]
    rho = np.hypot(rel[:, 0], rel[:, 1])
    phi = wrap_angle(np.arctan2(rel[:, 1], rel[:, 0]) - sp[2])
    in_view = (
        (rho >= fov.range_min)
        & (rho <= fov.range_max)
        & (phi >= fov.bearing_min)
        & (phi <= fov.bearing_max)
    )
    occluded = np.zeros_like(in_view)
    idx = np.flatnonzero(in_view)
    if idx.size < 2:
        return in_view, occluded
    # occluders: every tree nearer than the candidate whose disc reaches into the view
    cand = np.flatnonzero(rho <= fov.range_max + 2.0)
    half = np.arcsin(np.clip(r / np.maximum(rho, 1e-9), 0.0, 1.0))
    # (I, J): candidate i, occluder j
    pi_ = phi[idx][:, None]
    dphi = wrap_angle(phi[cand][None, :] - pi_)
    lo_i = -half[idx][:, None]
    hi_i = half[idx][:, None]
    lo_j = dphi - half[cand][None, :]
    hi_j = dphi + half[cand][None, :]
    nearer = (rho[cand][None, :] + r[cand][None, :] < rho[idx][:, None]) & (
        cand[None, :] != idx[:, None]
    )
    overlap = np.clip(np.minimum(hi_i, hi_j) - np.maximum(lo_i, lo_j), 0.0, None)
    # Union of overlaps is bounded by the sum; a conservative (larger) estimate is fine here:
    # intervals of distinct nearer trunks rarely overlap each other at the candidate's bearing.
    covered = np.sum(np.where(nearer, overlap, 0.0), axis=1)
    width = np.maximum(hi_i[:, 0] - lo_i[:, 0], 1e-12)
    occluded[idx] = covered / width >= occlusion_fraction
    return in_view, occluded


def negative_information(
    trees_xy: ArrayLike,
    diameters: ArrayLike,
    sensor_poses: ArrayLike,
    frame_ptr: ArrayLike,
    detections_xy: ArrayLike,
    fov: SensorFov,
    *,
    gate: float = 1.0,
    rule: Rule = "ohman2007",
    p_detect: float = 0.7,
    p_false: float = 0.05,
    min_expected: int = 3,
    occlusion_fraction: float = 0.5,
) -> NegativeInfoResult:
    """Count, per mapped tree, the frames that saw it and the frames that should have.

    Parameters
    ----------
    trees_xy : ndarray (N, 2), m, map frame
    diameters : ndarray (N,), m
    sensor_poses : ndarray (F, 3)
        Sensor pose (x, y, heading) in the map frame at every frame.
    frame_ptr : ndarray (F + 1,), int
        Detections of frame f are ``detections_xy[frame_ptr[f]:frame_ptr[f+1]]``.
    detections_xy : ndarray (K, 2), m, map frame
    fov : SensorFov
    gate : float, m
        A detection within ``gate`` of a tree counts as a hit.
    rule : {"ohman2007", "log_odds"}
        ``"ohman2007"``: remove when misses > hits (Öhman §2.2). ``"log_odds"`` (ours): remove
        when ``hits*log(p_d/p_f) + misses*log((1-p_d)/(1-p_f)) < 0``.
    p_detect, p_false : float in (0, 1)
        Detection / false-alarm probabilities of the log-odds rule.
    min_expected : int
        Trees expected in fewer frames than this are kept (not enough evidence either way).
    occlusion_fraction : float
        See :func:`expected_visibility`.

    Returns
    -------
    NegativeInfoResult

    Raises
    ------
    InputError
        On inconsistent shapes (ptr not matching the poses or the detections).
    """
    xy = np.asarray(trees_xy, dtype=np.float64).reshape(-1, 2)
    dia = np.asarray(diameters, dtype=np.float64).reshape(-1)
    if dia.shape[0] != xy.shape[0]:
        raise InputError(f"negative_information: {xy.shape[0]} trees but {dia.shape[0]} diameters.")
    sp = np.asarray(sensor_poses, dtype=np.float64).reshape(-1, 3)
    ptr = np.asarray(frame_ptr, dtype=np.int64).reshape(-1)
    det = np.asarray(detections_xy, dtype=np.float64).reshape(-1, 2)
    if ptr.shape[0] != sp.shape[0] + 1:
        raise InputError(
            f"negative_information: frame_ptr has {ptr.shape[0]} entries for {sp.shape[0]} "
            f"poses; it needs {sp.shape[0] + 1}."
        )
    if ptr.shape[0] and (ptr[0] != 0 or ptr[-1] != det.shape[0] or np.any(np.diff(ptr) < 0)):
        raise InputError(
            "negative_information: frame_ptr must start at 0, be non-decreasing and end at the "
            f"number of detections ({det.shape[0]}), got ends {ptr[0]}..{ptr[-1]}."
        )
    _check_rule("negative_information", rule, p_detect, p_false)
    n = xy.shape[0]
    hits = np.zeros(n, dtype=np.int64)
    misses = np.zeros(n, dtype=np.int64)
    occl = np.zeros(n, dtype=np.int64)
    radii = dia / 2.0
    if n:
        reach = fov.range_max + 2.0
        for f in range(sp.shape[0]):
            d2 = (xy[:, 0] - sp[f, 0]) ** 2 + (xy[:, 1] - sp[f, 1]) ** 2
            near = np.flatnonzero(d2 <= reach * reach)
            if near.size == 0:
                continue
            in_view, occluded = expected_visibility(
                xy[near], radii[near], sp[f], fov, occlusion_fraction=occlusion_fraction
            )
            if not np.any(in_view):
                continue
            z = det[ptr[f] : ptr[f + 1]]
            seen = np.zeros(near.size, dtype=bool)
            if z.shape[0]:
                dd = np.hypot(
                    xy[near][:, None, 0] - z[None, :, 0], xy[near][:, None, 1] - z[None, :, 1]
                )
                seen = np.any(dd <= gate, axis=1)
            expect = in_view & ~occluded
            hits[near[expect & seen]] += 1
            misses[near[expect & ~seen]] += 1
            occl[near[occluded]] += 1
    return _decide(hits, misses, occl, rule, p_detect, p_false, min_expected)


def _check_rule(who: str, rule: str, p_detect: float, p_false: float) -> None:
    if rule not in ("ohman2007", "log_odds"):
        raise ConfigError(f"{who}: unknown rule {rule!r}; use 'ohman2007' or 'log_odds'.")
    if not (0 < p_false < p_detect < 1):
        raise ConfigError(f"{who}: need 0 < p_false < p_detect < 1, got {p_false}, {p_detect}.")


def _decide(
    hits: NDArray[np.int64],
    misses: NDArray[np.int64],
    occl: NDArray[np.int64],
    rule: str,
    p_detect: float,
    p_false: float,
    min_expected: int,
) -> NegativeInfoResult:
    """Öhman's rule (remove when misses > hits) or the log-odds rule, with enough evidence."""
    llr = hits * math.log(p_detect / p_false) + misses * math.log((1 - p_detect) / (1 - p_false))
    enough = hits + misses >= min_expected
    remove = enough & (misses > hits) if rule == "ohman2007" else enough & (llr < 0)
    return NegativeInfoResult(hits, misses, occl, llr.astype(np.float64), ~remove)


def ray_pass_through(
    trees_xy: ArrayLike,
    diameters: ArrayLike,
    sensor_poses: ArrayLike,
    scans: ScanBatch,
    *,
    core_fraction: float = 0.5,
    position_tol: float = 0.05,
    hit_tol: float = 0.15,
    pass_margin: float = 0.5,
    rule: Rule = "ohman2007",
    p_detect: float = 0.7,
    p_false: float = 0.05,
    min_expected: int = 3,
) -> NegativeInfoResult:
    """Cast the raw scan rays through the mapped trees (Öhman et al. 2007, §2.2, Fig. 5).

    For every scan, every beam (a ray from the sensor pose at its bearing) is intersected with
    every mapped tree within reach, a disc of its diameter. A beam *crosses* a tree when it
    passes through its core, within ``min(core_fraction * r, r - position_tol)`` of the mapped
    centre, entering the disc at ``t_in`` and leaving at ``t_out``. With the beam's measured
    range ``R``:

    * ``t_in - hit_tol <= R <= t_out + hit_tol``: a valid measurement (hit) of the tree;
    * ``R >= t_out + pass_margin``, or no return while ``t_out + pass_margin`` is inside the
      scanner's ``range_max``: the beam passed *through* the tree (counted as a miss);
    * ``R < t_in - hit_tol``: something nearer stopped it (occluded; no evidence);
    * in between: ambiguous, not counted.

    Öhman: "If there are more rays passing through a tree than there are valid measurements of
    that tree, the tree is removed" -- ``rule="ohman2007"`` (misses > hits); ``"log_odds"`` as
    in :func:`negative_information`, per beam.

    Parameters
    ----------
    trees_xy : ndarray (N, 2), m, map frame
    diameters : ndarray (N,), m (NaN is treated as 0.2 m)
    sensor_poses : ndarray (S, 3) -- sensor x, y, heading in the map frame, one per scan
    scans : ScanBatch of S scans (ranges in the sensor frame; non-finite = no return)
    core_fraction : float in (0, 1]
        Only beams through the inner part of the disc count (0.5: the inner half).
    position_tol : float, m, >= 0
        Map position error to tolerate. A beam ``p`` from the mapped centre is ``<= p + e`` from
        the true centre of a trunk mapped ``e`` off, so with ``p < r - position_tol`` every
        counted beam meets the true trunk when ``e <= position_tol``: a true tree is never
        charged with a pass-through because of its map error. The price: false trees thinner
        than ``2 * position_tol`` (10 cm by default) get no counted beams and are never removed.
    hit_tol : float, m
        Slack around the disc for a hit (map position error + range noise; 0.15 m).
    pass_margin : float, m
        How far behind the disc's far side a return must be to count as passing through
        (0.5 m: larger than any map position error or diameter error we expect, so a grazing
        beam or a return from the true trunk's far half never counts against it).
    rule, p_detect, p_false, min_expected
        As in :func:`negative_information` (counts are beams, not frames).

    Returns
    -------
    NegativeInfoResult -- ``hits`` / ``misses`` / ``occluded`` are beam counts.

    Raises
    ------
    InputError
        When the poses do not match the scans.
    ConfigError
        On out-of-range thresholds.
    """
    xy = np.asarray(trees_xy, dtype=np.float64).reshape(-1, 2)
    dia = np.asarray(diameters, dtype=np.float64).reshape(-1)
    if dia.shape[0] != xy.shape[0]:
        raise InputError(f"ray_pass_through: {xy.shape[0]} trees but {dia.shape[0]} diameters.")
    sp = np.asarray(sensor_poses, dtype=np.float64).reshape(-1, 3)
    rng_all = np.atleast_2d(np.asarray(scans.ranges, dtype=np.float64))
    if sp.shape[0] != rng_all.shape[0]:
        raise InputError(
            f"ray_pass_through: {sp.shape[0]} sensor poses for {rng_all.shape[0]} scans; give "
            "one pose per scan."
        )
    if not 0 < core_fraction <= 1:
        raise ConfigError(
            f"ray_pass_through: core_fraction must be in (0, 1], got {core_fraction}."
        )
    if not position_tol >= 0:
        raise ConfigError(f"ray_pass_through: position_tol must be >= 0 m, got {position_tol}.")
    if not (hit_tol >= 0 and pass_margin > hit_tol):
        raise ConfigError(
            f"ray_pass_through: need 0 <= hit_tol < pass_margin, got {hit_tol}, {pass_margin}."
        )
    _check_rule("ray_pass_through", rule, p_detect, p_false)
    n = xy.shape[0]
    r = np.where(np.isfinite(dia) & (dia > 0), dia / 2.0, 0.1)
    hits = np.zeros(n, dtype=np.int64)
    misses = np.zeros(n, dtype=np.int64)
    occl = np.zeros(n, dtype=np.int64)
    n_b = rng_all.shape[1]
    rmax = float(scans.range_max) if math.isfinite(scans.range_max) else math.inf
    finite = rng_all[np.isfinite(rng_all)]
    far = rmax if math.isfinite(rmax) else float(finite.max(initial=0.0))
    reach = far + float(r.max(initial=0.0))  # trees beyond cannot meet a beam's return
    rel_ang = scans.angle_min + scans.angle_increment * np.arange(n_b)
    core = np.minimum(core_fraction * r, r - position_tol)
    for f in range(sp.shape[0]):
        rel = xy - sp[f, :2]
        near = np.flatnonzero(np.hypot(rel[:, 0], rel[:, 1]) <= reach)
        if near.size == 0:
            continue
        ang = sp[f, 2] + rel_ang
        ux, uy = np.cos(ang), np.sin(ang)
        cx, cy = rel[near, 0][:, None], rel[near, 1][:, None]
        t = cx * ux + cy * uy  # along the beam, (T, B)
        perp = np.abs(cx * uy - cy * ux)
        cross = (t > 0) & (perp < core[near][:, None])
        if not cross.any():
            continue
        half = np.sqrt(np.maximum(r[near][:, None] ** 2 - perp**2, 0.0))
        t_in, t_out = t - half, t + half
        R = rng_all[f][None, :]
        ret = np.isfinite(R) & (scans.range_min < R)
        hit = cross & ret & (t_in - hit_tol <= R) & (t_out + hit_tol >= R)
        through = cross & np.where(ret, t_out + pass_margin <= R, t_out + pass_margin < rmax)
        blocked = cross & ret & (t_in - hit_tol > R)
        hits[near] += hit.sum(axis=1)
        misses[near] += through.sum(axis=1)
        occl[near] += blocked.sum(axis=1)
    return _decide(hits, misses, occl, rule, p_detect, p_false, min_expected)


def _keep_trees(stem_map: StemMap, res: NegativeInfoResult) -> StemMap:
    """The trees ``res`` keeps, with confidence hits / (hits + misses)."""
    from dataclasses import replace

    kept = []
    for t, keep, h, m in zip(stem_map.trees, res.keep, res.hits, res.misses, strict=True):
        if keep:
            tot = int(h + m)
            kept.append(replace(t, confidence=float(h / tot) if tot else t.confidence))
    return StemMap(tuple(kept), frame=stem_map.frame, crs=stem_map.crs)


def remove_false_trees_by_rays(
    stem_map: StemMap, sensor_poses: ArrayLike, scans: ScanBatch, **kwargs: object
) -> tuple[StemMap, NegativeInfoResult]:
    """Apply :func:`ray_pass_through` to a stem map and drop the trees it rejects (Öhman Fig. 5).

    Surviving trees keep their ids; ``confidence`` is set to hits / (hits + misses) (beams).
    Keyword arguments go to :func:`ray_pass_through`.
    """
    res = ray_pass_through(
        stem_map.xy,
        stem_map.diameters if len(stem_map) else np.zeros(0),
        sensor_poses,
        scans,
        **kwargs,  # type: ignore[arg-type]
    )
    return _keep_trees(stem_map, res), res


def remove_false_trees(
    stem_map: StemMap,
    sensor_poses: ArrayLike,
    frame_ptr: ArrayLike,
    detections_xy: ArrayLike,
    fov: SensorFov,
    **kwargs: object,
) -> tuple[StemMap, NegativeInfoResult]:
    """Apply :func:`negative_information` to a stem map and drop the trees it rejects.

    Surviving trees keep their ids; ``confidence`` is set to hits / (hits + misses).
    Keyword arguments go to :func:`negative_information`.
    """
    res = negative_information(
        stem_map.xy,
        stem_map.diameters if len(stem_map) else np.zeros(0),
        sensor_poses,
        frame_ptr,
        detections_xy,
        fov,
        **kwargs,  # type: ignore[arg-type]
    )
    return _keep_trees(stem_map, res), res


def remove_false_trees_after(
    result: SlamResult,
    problem: SlamProblem,
    *,
    range_min: float = 1.0,
    range_max: float | None = None,
    **kwargs: object,
) -> tuple[StemMap, NegativeInfoResult]:
    """Negative-information post-step for any back-end's result.

    Sensor poses come from ``result.trajectory`` and ``problem.sensor_offset``, the detections
    from ``problem.frames`` mapped with those poses, the bearing window from ``problem.fov`` and
    the range window from ``range_min`` .. ``range_max`` (default ``min(problem.max_range,
    30 m)``: the range where the detector can be expected to find a trunk). Other keyword
    arguments go to :func:`negative_information`.
    """
    from stemmap.slam.base import observation_to_world, sensor_poses

    fr = problem.frames
    poses = result.trajectory.poses
    if poses.shape[0] != len(fr):
        raise InputError(
            f"remove_false_trees_after: the trajectory has {poses.shape[0]} poses but the problem "
            f"has {len(fr)} frames; pass the result of running this problem."
        )
    rmax = float(min(problem.max_range, 30.0)) if range_max is None else float(range_max)
    fov = SensorFov(problem.fov[0], problem.fov[1], range_min, rmax)
    det = observation_to_world(poses[fr.frame_index], fr.ranges, fr.bearings, problem.sensor_offset)
    sp = sensor_poses(poses, problem.sensor_offset)
    return remove_false_trees(result.stem_map, sp, fr.ptr, det, fov, **kwargs)
