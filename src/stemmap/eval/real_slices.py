"""Breast-height slices of real point clouds and virtual 2D laser scans made from them.

Shared by ``benchmarks/real_geometry.py`` (detector recall and DBH error on real trunk
geometry) and ``benchmarks/scan_fits_real.py`` (circle fits on real arcs).

A slice is the part of a real terrestrial / mobile lidar cloud between 1.2 and 1.4 m above the
ground (:data:`SLICES` says how each cloud's ground is found). Its points are clustered on a
5 cm occupancy grid; a cluster seen (nearly) all round (inliers in >= 250 degrees of 10-degree
sectors around its centre) gets a *reference* circle (:func:`ring_reference`): RANSAC (the
circle whose inliers cover the most sectors) then a geometric (orthogonal-distance) fit of the
ring, with returns farther than 3 robust sigmas from it (branches, needles) trimmed and the fit
repeated. The reference's own RMS and inlier fraction are reported with it. The sectors the
lidar did not see are filled with points on the reference circle (or, ``fill="outline"``,
along the outline joined across them: :func:`_fill_unseen_sectors`), so that the trunk is
solid in the virtual scans.

A virtual 2D scan from a vantage point keeps, per beam, what a 2D scanner at 1.3 m would see
of the whole slice (every trunk, branch and bush occludes what is behind it):

- ``"nearest"``: a first-echo scanner whose beam fills the angular step: the nearest slice
  point within the beam's angular cell (width = the angular resolution).
- ``"averaging"``: a SICK LMS2xx-class scanner: the beam footprint (``footprint_deg``, 0.25 deg
  by default, centred on the beam) is cut into sub-rays (25 by default: 5 before Dec 5); each
  sub-ray returns the nearest point in its sub-cell and the beam reports the power-weighted
  (``1/r^2``) mean range of the sub-rays that hit, the simulator's mixed-pixel model
  (:mod:`stemmap.sim.footprint`; the plain mean before Dec 5). Its *return threshold*
  (``min_hit_fraction``, Dec 4) is the share of the footprint that must hit for the beam to
  return: 0 (the default, every round's benchmark) returns when any sub-ray hits; 0.5 when half
  the footprint hits (what the ``stemmap`` detector's edge model assumes);
  ``beam_profile="gaussian"`` weights the sub-rays by a Gaussian beam's energy (1/e^2 at the
  footprint's edges) in both the threshold and the mean range: an energy threshold, as a real
  time-of-flight scanner's echo detection (the distance a SICK LMS200 reports depends on the
  blocked radiant power rather than the blocked area: Sanz-Cortiella et al. 2011).

Gaussian range noise can be added per beam. Each beam also carries the index of the
reference trunk it hit (-1 = anything else), which tells which trunks are visible.

``background="ground"`` (fifteenth round) adds what a real scanner at breast height sees
besides the trunks: the scan plane pitched down by a few degrees (:class:`Mount`) cuts the
same cloud's ground and understory below the slice and meets the ground plane ahead
(:mod:`stemmap.eval.scan_background`; a flat plane for the clouds without ground).
``background="none"`` (the default) is the trunks-only scan of the first fourteen rounds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from stemmap.errors import InputError
from stemmap.eval.scan_background import (
    GroundSurface,
    Mount,
    Relief,
    band_points,
    ground_ranges,
    ground_surface,
)
from stemmap.sim.footprint import footprint_ranges
from stemmap.types import FloatArray, ScanBatch

__all__ = [
    "FILLS",
    "SLICES",
    "GroundSurface",
    "Mount",
    "RealSlice",
    "Relief",
    "SliceSpec",
    "cluster_grid",
    "load_slice",
    "noisy_batch",
    "reference_jackknife",
    "ring_reference",
    "surface_point_radius",
    "virtual_scans",
]


@dataclass(frozen=True)
class SliceSpec:
    """Where a slice comes from: ``path`` under the datasets folder and how heights are
    measured: ``"as_is"`` (the file is already a breast-height slice), ``"ground"`` (heights
    above a 1 m grid of lowest points, :func:`stemmap.cloud.ground.fit_ground`) or
    ``"lowest"`` (a single tree without ground: heights above the 0.1 % lowest point; only the
    points within 0.5 m of the stem axis can be the trunk, the others are branches: the disc
    about the stem base, the median xy of the points below 0.5 m, re-centred on its ring fit,
    :func:`_stem_disc`). ``cell``: clustering grid, metres (coarser for sparse
    clouds). ``reference_complete``: every trunk of the slice has a reference or a partial ring,
    so a detection on anything else is a false alarm (single trees: one stem among branches and
    needles; the FORTLS slice: its 20 circles only). False for the single-scan TreeLS plot,
    where 8 further stems are seen by 5-30 points or over < 250 degrees (clusters the
    detectors find at stem-like radii of 4-15 cm): no precision is scored there.
    ``ground_points``: the cloud holds its ground (the TreeLS plot, 10 x 10 m; TreeLS pine and
    spruce, a 2.3 x 1.9 m patch around the stem base), which gives the virtual scans'
    ground plane and understory (:func:`stemmap.eval.scan_background.ground_surface`)."""

    path: str
    heights: Literal["as_is", "ground", "lowest"]
    z_lo: float = 1.2
    z_hi: float = 1.4
    min_ring_points: int = 100
    cell: float = 0.05
    min_coverage_deg: float = 250.0
    reference_complete: bool = True
    ground_points: bool = False


#: Every real cloud of the shared datasets that has trunks at breast height.
SLICES: dict[str, SliceSpec] = {
    "fortls_slice": SliceSpec("fortls_slice/diameters.laz", "as_is", min_ring_points=500),
    "treels_pine_plot": SliceSpec(
        "treels/pine_plot.laz",
        "ground",
        min_ring_points=30,
        reference_complete=False,
        ground_points=True,
    ),
    "treels_pine": SliceSpec("treels/pine.laz", "lowest", ground_points=True),
    "treels_spruce": SliceSpec("treels/spruce.laz", "lowest", ground_points=True),
    "lidr_dbh": SliceSpec("lidr_dbh/dbh.laz", "as_is"),
    "archi_tree1": SliceSpec(
        "archi/Tree_1_point_cloud.las", "lowest", min_ring_points=30, cell=0.1
    ),
    "archi_tree2": SliceSpec("archi/Tree_2_point_cloud.las", "lowest"),
}


@dataclass(frozen=True)
class RealSlice:
    """A breast-height slice: ``xy`` (N, 2) points, ``labels`` (N,) reference trunk per point
    (-1 = not a reference trunk), ``refs`` one dict per reference trunk (x, y, diameter,
    ring_rms_m, inlier_fraction, coverage_deg, n_points); ``partial`` the ring fits of
    clusters seen over less than the spec's ``min_coverage_deg`` (no reference: they stay in
    the scans as occluders and are neither hits nor false alarms); ``ground`` the ground
    plane and understory below the slice (:class:`GroundSurface`; a flat plane without
    understory where the cloud has no ground)."""

    name: str
    xy: FloatArray
    labels: NDArray[np.int64]
    refs: list[dict[str, float]]
    partial: list[dict[str, float]]
    ground: GroundSurface | None = None

    @property
    def centers(self) -> FloatArray:
        return np.array([[r["x"], r["y"]] for r in self.refs]).reshape(-1, 2)

    @property
    def diameters(self) -> FloatArray:
        return np.array([r["diameter"] for r in self.refs])


def cluster_grid(xy: FloatArray, cell: float) -> NDArray[np.int64]:
    """Label points by 8-connected components of an occupancy grid of ``cell`` metres.

    Equivalent to single-linkage clustering at ~cell spacing (DBSCAN with eps ~ cell and
    min_samples = 1) but ~100x faster here: the trunks in a slice are metres apart.
    """
    ij = np.floor((xy - xy.min(axis=0)) / cell).astype(np.int64)
    grid = np.zeros(tuple(ij.max(axis=0) + 1), dtype=bool)
    grid[ij[:, 0], ij[:, 1]] = True
    lab, _ = ndimage.label(grid, structure=np.ones((3, 3), dtype=bool))
    return np.asarray(lab[ij[:, 0], ij[:, 1]], dtype=np.int64) - 1


def _sectors(q: FloatArray, sector_deg: float = 10.0) -> NDArray[np.int64]:
    """The ``sector_deg`` sector (0 .. 360 / sector_deg - 1, from -180 degrees) of each offset
    ``q`` (N, 2) from a centre."""
    n = round(360.0 / sector_deg)
    return (
        np.floor((np.degrees(np.arctan2(q[:, 1], q[:, 0])) + 180.0) / sector_deg).astype(np.int64)
        % n
    )


def _ransac_circle(
    pts: FloatArray, tol: float, rng: np.random.Generator, n_trials: int = 300
) -> NDArray[np.bool_]:
    """Inliers (within ``tol`` of the circle) of the 3-point circle whose inliers cover the most
    10-degree sectors around its centre, the most inliers among those, of ``n_trials`` random
    triples (Fischler & Bolles 1981, scored by angular coverage): the trunk among branches.
    Scoring by the inlier count alone (before Dec 5) let a larger circle through one side and
    the two ends of a lobed, sparse ring seen over 260 degrees win (aRchi tree 1: 63.7 cm over
    200 degrees in 14 of 20 seeds, against 54-57 cm over 260-280 degrees); a trunk's ring is the
    circle seen all round."""
    best = np.ones(pts.shape[0], dtype=bool)
    best_key = (0, 0)
    for _ in range(n_trials):
        a, b, c = pts[rng.choice(pts.shape[0], 3, replace=False)]
        d = 2.0 * (a[0] * (b[1] - c[1]) + b[0] * (c[1] - a[1]) + c[0] * (a[1] - b[1]))
        if abs(d) < 1e-12:
            continue
        a2, b2, c2 = a @ a, b @ b, c @ c
        ux = (a2 * (b[1] - c[1]) + b2 * (c[1] - a[1]) + c2 * (a[1] - b[1])) / d
        uy = (a2 * (c[0] - b[0]) + b2 * (a[0] - c[0]) + c2 * (b[0] - a[0])) / d
        r = math.hypot(a[0] - ux, a[1] - uy)
        if not 0.02 < r < 1.0:
            continue
        inl = np.abs(np.hypot(pts[:, 0] - ux, pts[:, 1] - uy) - r) <= tol
        n = int(inl.sum())
        top = min(n, 36)  # the most sectors n inliers can cover
        if top < best_key[0] or (top == best_key[0] and n <= best_key[1]):
            continue  # cannot beat the best
        cov = int(np.unique(_sectors(pts[inl] - np.array([ux, uy]))).size)
        if (cov, n) > best_key:
            best, best_key = inl, (cov, n)
    return best


def ring_reference(
    ring: FloatArray,
    *,
    min_coverage_deg: float = 0.0,
    trim_sigmas: float = 3.0,
    seed: int = 0,
) -> tuple[dict[str, float], NDArray[np.bool_]] | None:
    """Reference circle of a trunk seen (nearly) all round.

    A RANSAC circle (2 cm tolerance) separates the trunk from branches and needles in the
    cluster; then a geometric fit of its inliers, returns farther than ``trim_sigmas`` robust
    sigmas (1.4826 MAD, floor 5 mm) trimmed, fit repeated (three times in all).

    Returns the reference (x, y, diameter, ring_rms_m over the inliers, inlier_fraction,
    coverage_deg: 10-degree sectors around the centre holding inliers) and the inlier mask, or
    None when the fit fails or the coverage is below ``min_coverage_deg`` (a trunk seen from one
    side only has no trustworthy reference).
    """
    from stemmap.scan.circle import fit_circle_ours

    inl = _ransac_circle(ring, 0.02, np.random.default_rng(seed))
    fit = None
    for _ in range(3):
        if inl.sum() < 10:
            return None
        fit = fit_circle_ours(ring[inl], edges=(False, False))
        if not fit:
            return None
        res = np.hypot(*(ring - fit.center).T) - fit.radius
        mad = 1.4826 * float(np.median(np.abs(res[inl] - np.median(res[inl]))))
        inl = np.abs(res) <= trim_sigmas * max(mad, 0.005)
    assert fit is not None
    q = ring[inl] - fit.center
    sectors = np.unique(_sectors(q))
    coverage = 10.0 * sectors.size
    if coverage < min_coverage_deg:
        return None
    res = np.hypot(*q.T) - fit.radius
    ref = {
        "x": float(fit.center[0]),
        "y": float(fit.center[1]),
        "diameter": float(fit.diameter),
        "ring_rms_m": float(np.sqrt(np.mean(res * res))),
        "inlier_fraction": float(inl.mean()),
        "coverage_deg": float(coverage),
        "n_points": int(inl.sum()),
    }
    return ref, inl


def _read_xyz(path: Path) -> FloatArray:
    import laspy

    if not path.is_file():
        raise InputError(
            f"{path} not found; set STEMMAP_DATASETS to the shared datasets folder "
            "(see ../shared/datasets/README.md)."
        )
    las = laspy.read(path)
    return np.column_stack((las.x, las.y, las.z)).astype(np.float64)


def reference_jackknife(sl: RealSlice, t: int, sector_deg: float = 30.0) -> dict[str, Any]:
    """How far the reference diameter of trunk ``t`` can be trusted (issue 11, fifth round):
    its ring RMS, coverage, the sectors filled (with the outline joined across them), and the
    smallest / largest change of the diameter (cm) when the ring is refitted
    (:func:`ring_reference`) with each ``sector_deg`` sector of its own points left out
    (jackknife; Efron & Tibshirani 1993 ch. 11). A ring that is a circle moves by millimetres;
    a sparse, lobed outline seen over little more than the coverage bound moves by
    centimetres, and so does any diameter measured against it."""
    ref = sl.refs[t]
    n_own = int(ref["n_points"])
    pts = sl.xy[sl.labels == t][:n_own]  # the ring's inliers; the filled sectors come after
    q = pts - np.array([ref["x"], ref["y"]])
    sector = _sectors(q, sector_deg)
    d = []
    for s in np.unique(sector):
        got = ring_reference(pts[sector != s])
        if got is not None:
            d.append(100.0 * (got[0]["diameter"] - ref["diameter"]))
    return {
        "ring_rms_mm": round(1000.0 * ref["ring_rms_m"], 1),
        "coverage_deg": ref["coverage_deg"],
        "filled_deg": ref.get("filled_sectors_deg", 0.0),
        "ring_points": n_own,
        "jackknife_change_cm": [round(min(d), 2), round(max(d), 2)] if d else None,
    }


#: How :func:`load_slice` fills a reference trunk's unseen sectors (:func:`_fill_unseen_sectors`):
#: ``"circle"`` (the reference circle; the benchmark's default) or ``"outline"`` (the outline
#: joined across them from the seen sectors' median radii; Dec 5, an option).
FILLS = ("circle", "outline")


def load_slice(datasets_dir: Path | str, name: str, fill: str = "circle") -> RealSlice:
    """The breast-height slice ``name`` (a key of :data:`SLICES`) with its ring references.

    Coordinates are shifted so that the slice's bounding-box centre is the origin. ``fill``
    (:data:`FILLS`): what stands in each reference trunk's unseen sectors.
    """
    try:
        spec = SLICES[name]
    except KeyError:
        raise InputError(f"unknown real slice {name!r}; choose one of {sorted(SLICES)}.") from None
    if fill not in FILLS:
        raise InputError(f"fill must be one of {FILLS}, got {fill!r}.")
    xyz = _read_xyz(Path(datasets_dir) / spec.path)
    base_xy = None
    h = np.zeros(0)
    if spec.heights == "as_is":
        keep = np.ones(xyz.shape[0], dtype=bool)
    else:
        if spec.heights == "ground":
            from stemmap.cloud.ground import fit_ground, normalize_heights

            h = normalize_heights(xyz, fit_ground(xyz, cell=1.0))[:, 2]
        else:
            h = xyz[:, 2] - float(np.quantile(xyz[:, 2], 0.001))
            base_xy = np.median(xyz[h < 0.5, :2], axis=0)
        keep = (h >= spec.z_lo) & (h <= spec.z_hi)
    xy = xyz[keep, :2]
    if xy.shape[0] < spec.min_ring_points:
        raise InputError(f"{spec.path}: only {xy.shape[0]} points at breast height.")
    shift = 0.5 * (xy.min(axis=0) + xy.max(axis=0))
    xy = xy - shift
    clusters = cluster_grid(xy, spec.cell)
    if base_xy is not None:  # single tree: the stem is within 0.5 m of its axis
        clusters = np.where(_stem_disc(xy, base_xy - shift), 0, -1)
    labels = np.full(xy.shape[0], -1, dtype=np.int64)
    refs: list[dict[str, float]] = []
    partial: list[dict[str, float]] = []
    for lab in np.flatnonzero(np.bincount(clusters[clusters >= 0]) >= spec.min_ring_points):
        idx = np.flatnonzero(clusters == lab)
        got = ring_reference(xy[idx])
        if got is None:
            continue
        ref, inl = got
        if ref["coverage_deg"] < spec.min_coverage_deg:
            partial.append(ref)
            continue
        labels[idx[inl]] = len(refs)
        pts = _fill_unseen_sectors(xy[idx[inl]], ref, xy[idx] if fill == "outline" else None)
        ref["filled_sectors_deg"] = 360.0 - ref["coverage_deg"]
        xy = np.vstack((xy, pts))
        labels = np.concatenate((labels, np.full(pts.shape[0], len(refs), dtype=np.int64)))
        refs.append(ref)
    ground = GroundSurface.flat(
        "flat model: the file is a breast-height slice (no ground)"
        if spec.heights == "as_is"
        else "flat model: a segmented tree without ground"
    )
    if spec.ground_points:
        stems = [(r["x"], r["y"], 0.5 * r["diameter"]) for r in (*refs, *partial)]
        pts = np.column_stack((xyz[:, :2] - shift, xyz[:, 2]))
        if base_xy is None:  # a ground raster: its points within 10 cm
            on_ground = np.abs(h) <= 0.1
        else:  # a single tree: the lowest 15 cm away from the stem base
            b = base_xy - shift
            stems.append((float(b[0]), float(b[1]), 0.3))
            on_ground = (h < 0.15) & (np.hypot(*(pts[:, :2] - b).T) > 0.3)
        ground = ground_surface(pts, h, on_ground, spec.z_lo, np.array(stems).reshape(-1, 3))
    return RealSlice(name=name, xy=xy, labels=labels, refs=refs, partial=partial, ground=ground)


def _stem_disc(xy: FloatArray, base: FloatArray, radius: float = 0.5) -> NDArray[np.bool_]:
    """The points of a single tree's slice within ``radius`` of its stem axis: first the disc
    about the stem base (the median xy of the lowest 0.5 m), then, while the set changes (at
    most three times), the disc about the ring fit of the set (:func:`ring_reference`). The
    base alone is off the axis where the lowest metre is seen from one side or flares: aRchi
    tree 1's base lies 21 cm west of its breast-height axis, and the 0.5 m disc about it cut
    the 6 east-most stem points (0.52-0.60 m from it), which then stood 7-15 cm outside the
    filled ring as foreign points (Dec 5, "aRchi tree 1: the reference settled")."""
    near = np.hypot(*(xy - base).T) <= radius
    for _ in range(3):
        got = ring_reference(xy[near]) if near.sum() >= 10 else None
        if got is None:
            break
        again = np.hypot(xy[:, 0] - got[0]["x"], xy[:, 1] - got[0]["y"]) <= radius
        if np.array_equal(again, near):
            break
        near = again
    return near


def _fill_unseen_sectors(
    ring: FloatArray, ref: dict[str, float], outline: FloatArray | None = None
) -> FloatArray:
    """Points every 5 mm (of the reference circle's arc) in the 10-degree sectors where the ring
    has no return (the side the lidar did not see): a solid trunk, so that a virtual beam
    cannot pass through the unseen side and return from the inside of the far wall.

    Without ``outline`` the points lie on the reference circle (the benchmark's default). With
    ``outline`` (the trunk's points; ``load_slice(fill="outline")``, Dec 5) the radius about the
    reference centre in an unseen sector is interpolated (linearly in angle, around the
    circle) between the median radii of the nearest seen sectors' ``outline`` points (those
    within 30 % of the reference radius of the circle), so the fill joins the seen outline at
    both ends. On a round ring both are the circle; on a lobed or oblong one (aRchi tree 1,
    56 x 66 cm calipers) the circle leaves a step of 3-12 cm at each end of the unseen side,
    where the seen outline stands outside it: a notch no trunk has."""
    c = np.array([ref["x"], ref["y"]])
    r = 0.5 * ref["diameter"]
    seen = np.zeros(36, dtype=bool)
    seen[_sectors(ring - c)] = True
    phi = np.arange(-math.pi, math.pi, 0.005 / r)
    phi = phi[~seen[_sectors(np.column_stack((np.cos(phi), np.sin(phi))))]]
    if outline is None:
        return c + r * np.column_stack((np.cos(phi), np.sin(phi)))
    q = outline - c
    rad = np.hypot(*q.T)
    keep = np.abs(rad - r) <= 0.3 * r
    sec = _sectors(q[keep])
    med = np.full(36, np.nan)
    for k in np.unique(sec):
        med[k] = np.median(rad[keep][sec == k])
    known = np.flatnonzero(seen & np.isfinite(med))
    mid = np.radians(-175.0 + 10.0 * np.arange(36))  # sector centres
    if known.size == 0:
        rr = np.full(phi.shape, r)
    else:
        xp = np.concatenate((mid[known] - 2.0 * math.pi, mid[known], mid[known] + 2.0 * math.pi))
        rr = np.interp(phi, xp, np.tile(med[known], 3))
    return c + rr[:, None] * np.column_stack((np.cos(phi), np.sin(phi)))


def surface_point_radius(xy: FloatArray) -> float:
    """Disc radius that closes a sampled surface: half the 90th percentile of the
    nearest-neighbour spacing of the distinct points (most gaps between neighbours are
    bridged), at least 2 mm."""
    from scipy.spatial import cKDTree

    u = np.unique(xy, axis=0)
    if u.shape[0] < 2:
        return 0.002
    d, _ = cKDTree(u).query(u, k=2)
    return max(0.5 * float(np.quantile(d[:, 1], 0.9)), 0.002)


def virtual_scans(
    xy: FloatArray,
    labels: NDArray[np.int64],
    vantages: FloatArray,
    *,
    resolution_deg: float,
    model: Literal["nearest", "averaging"] = "nearest",
    footprint_deg: float = 0.25,
    sub_rays: int = 25,
    min_hit_fraction: float = 0.0,
    beam_profile: Literal["uniform", "gaussian"] = "uniform",
    max_range: float = 30.0,
    point_radius: float | None = None,
    centers: FloatArray | None = None,
    background: Literal["none", "ground"] = "none",
    ground: GroundSurface | None = None,
    mount: Mount | None = None,
    headings: FloatArray | None = None,
    relief: Relief | None = None,
) -> tuple[FloatArray, NDArray[np.int64]]:
    """Noise-free 360-degree 2D scans of a slice from each vantage point.

    Beam k of every scan points at bearing ``-pi + k * resolution`` (the x axis of the slice is
    the scanner's 0 bearing). See the module docstring for the two scanner models. A cloud is
    a sample of the bark, not a surface: each point is taken as a disc of ``point_radius``
    (default :func:`surface_point_radius`) so that narrow (sub-)rays cannot pass between the
    points of a trunk and return from the inside of its far side; a (sub-)cell returns the
    range of the nearest part of the disc inside its angular cell. With ``centers`` (one per
    reference trunk) the points of a reference trunk facing away from the vantage are culled
    (a solid trunk hides its own far side) and its discs are centred ``point_radius`` inside
    the sampled surface, so that their envelope is that surface: without this, every
    silhouette of a sparse cloud was widened by ``point_radius`` on each side (+2 x
    point_radius of diameter in the detectors' estimates: +1.6 cm on the TreeLS pine plot,
    8 mm discs; issue 11 diagnosis).

    ``background="ground"``: the scan plane of ``mount`` (default :class:`Mount`: 1.3 m,
    pitched down 3 degrees) pitched towards ``headings[v]`` (radians, default 0) from each
    vantage also returns from the points of ``ground`` (default a flat plane without
    understory) below the slice that it passes through (:func:`band_points`, discs like the
    slice's, each trunk still hides them) and, on every (sub-)ray, from the ground plane where
    it meets it first (:func:`ground_ranges`; with ``relief`` the first bump of that
    micro-relief the beam grazes, else the plane itself): a beam that misses the trunks hits
    the ground or the understory, and a trunk behind the ground's line is hidden. The trunks
    themselves stay the breast-height slice (the pitch moves the beam by <= 0.8 m of height at
    15 m; the slice stands for the stem there). Ranges are horizontal, as the slice's.

    The averaging scanner's return threshold: a beam returns when the share of its footprint
    whose sub-rays hit something is at least ``min_hit_fraction`` (0 = any sub-ray hits, the
    default; 0.5 = half the footprint, the edge model of the ``stemmap`` detector). With
    ``beam_profile="uniform"`` the share is the fraction of the ``sub_rays`` sub-rays that hit
    (at least ``ceil(min_hit_fraction * sub_rays)``, and >= 1, as
    :class:`stemmap.sim.scanner.ScannerModel`), so it moves in steps of ``1 / sub_rays`` of the
    footprint (a sub-ray counts when anything is in its sub-cell); the range is the
    ``1/r^2``-weighted mean of the sub-rays that hit
    (:func:`stemmap.sim.footprint.footprint_ranges`, the simulator's model). With ``"gaussian"``
    each sub-ray carries the energy of a Gaussian beam at its offset ``d`` from the beam axis,
    ``exp(-2 (2 d / footprint)^2)`` (1/e^2 at the footprint's edge): the share is the energy
    that hit over the beam's, the range weighted by energy / r^2 (the received power). A beam
    that does not reach the threshold reports no return (inf, -1) even where some sub-rays hit;
    sub-rays that hit a farther object (another trunk, the ground) count towards the share and
    the mean as the trunk's do (mixed pixels). Ignored by the ``nearest`` model.

    Returns
    -------
    ranges : ndarray (V, N), metres (inf = no return within ``max_range``)
    hit : ndarray (V, N), the reference trunk each beam returned from (-1 = other or none); for
        an averaging beam the trunk of the nearest sub-ray
    """
    if model not in ("nearest", "averaging"):
        raise InputError(f"scanner model must be 'nearest' or 'averaging', got {model!r}.")
    if background not in ("none", "ground"):
        raise InputError(f"background must be 'none' or 'ground', got {background!r}.")
    if not 0.0 <= min_hit_fraction <= 1.0:
        raise InputError(f"min_hit_fraction must be in [0, 1], got {min_hit_fraction!r}.")
    if beam_profile not in ("uniform", "gaussian"):
        raise InputError(f"beam_profile must be 'uniform' or 'gaussian', got {beam_profile!r}.")
    res = math.radians(resolution_deg)
    n_beams = round(2.0 * math.pi / res)
    vantages = np.atleast_2d(np.asarray(vantages, dtype=np.float64))
    ranges = np.full((vantages.shape[0], n_beams), np.inf)
    hit = np.full((vantages.shape[0], n_beams), -1, dtype=np.int64)
    if model == "nearest":
        sub, n_sub, width = res, 1, res
    else:
        width = math.radians(footprint_deg)
        n_sub = max(int(sub_rays), 1)
        sub = width / n_sub
    if point_radius is None:
        point_radius = surface_point_radius(xy)
    step = max(round(res / sub), 1)  # sub-cells per beam step (1 for "nearest")
    xy = np.asarray(xy, dtype=np.float64)
    out = np.zeros((0, 2))
    t = labels >= 0
    if centers is not None:
        out = xy[t] - np.asarray(centers, dtype=np.float64)[labels[t]]  # outward normals
        # the discs' outer envelope is the sampled surface: centres point_radius inside it
        nrm = np.hypot(out[:, 0], out[:, 1])
        xy = xy.copy()
        xy[t] -= point_radius * out / np.maximum(nrm, 1e-12)[:, None]
    with_ground = background == "ground"
    surface = ground if ground is not None else GroundSurface.flat("flat model")
    mount = mount if mount is not None else Mount()
    heads = np.zeros(vantages.shape[0]) if headings is None else np.asarray(headings, float)
    # bearing of every (sub-)ray: beam k's sub-cell j is centred at -pi + (k step + j + 1/2)
    # sub - width / 2
    cells = np.arange(n_beams)[:, None] * step + np.arange(n_sub)[None, :]
    sub_bearing = np.asarray((cells + 0.5) * sub - 0.5 * width - math.pi, dtype=np.float64)
    # energy of each sub-ray (gaussian: a beam of 1/e^2 full width = the footprint)
    u_sub = ((np.arange(n_sub) + 0.5) * sub - 0.5 * width) / (0.5 * width)
    energy = np.exp(-2.0 * u_sub * u_sub) if beam_profile == "gaussian" else np.ones(n_sub)
    energy /= energy.sum()
    for v, o in enumerate(vantages):
        xy_v, lab_v = xy, labels
        if with_ground:
            extra = band_points(surface, o, float(heads[v]), mount)
            xy_v = np.vstack((xy, extra))
            lab_v = np.concatenate((labels, np.full(extra.shape[0], -1, dtype=np.int64)))
        q = xy_v - o
        rho = np.hypot(q[:, 0], q[:, 1])
        near = (rho <= max_range) & (rho > point_radius)
        if centers is not None:
            tv = np.flatnonzero(t)  # the trunk points come first: the band points are -1
            near[tv] &= np.einsum("ij,ij->i", out, -q[tv]) > 0.0
        q, rho, lab = q[near], rho[near], lab_v[near]
        order = np.argsort(rho, kind="stable")
        q, rho, lab = q[order], rho[order], lab[order]
        th = np.arctan2(q[:, 1], q[:, 0]) + math.pi  # [0, 2 pi]
        # each point is a disc of point_radius: it covers every sub-cell its angular interval
        # touches (a surface, not a sieve the sub-rays pass through)
        half = np.arcsin(np.minimum(point_radius / rho, 1.0))
        lo = np.floor((th - half + 0.5 * width) / sub).astype(np.int64)
        hi = np.floor((th + half + 0.5 * width) / sub).astype(np.int64)
        cnt = hi - lo + 1
        idx = np.repeat(np.arange(rho.shape[0]), cnt)  # still sorted by range
        cell = np.repeat(lo - np.cumsum(cnt) + cnt, cnt) + np.arange(idx.shape[0])
        k = np.floor_divide(cell, step)
        j = cell - k * step
        ok = j < n_sub
        k, j, idx = k[ok] % n_beams, j[ok], idx[ok]
        flat = k * n_sub + j
        # first echo of the (sub-)cell: the nearest part of the disc inside the cell's angular
        # sector: rho - point_radius when the disc centre is inside it, else where the
        # sector's nearer boundary ray enters the disc (convexity)
        dlt = np.maximum(np.abs((cell[ok] + 0.5) * sub - 0.5 * width - th[idx]) - 0.5 * sub, 0.0)
        off = rho[idx] * np.sin(dlt)
        enter = rho[idx] * np.cos(dlt) - np.sqrt(np.maximum(point_radius**2 - off * off, 0.0))
        order = np.lexsort((enter, flat))
        first = order[np.unique(flat[order], return_index=True)[1]]  # nearest entry per cell
        f = flat[first]
        sub_r = np.full((n_beams, n_sub), np.inf)
        sub_l = np.full((n_beams, n_sub), -1, dtype=np.int64)
        sub_r.reshape(-1)[f] = enter[first]
        sub_l.reshape(-1)[f] = lab[idx[first]]
        if with_ground:  # the ground plane where the (sub-)ray meets it first
            g = ground_ranges(
                surface, sub_bearing.ravel(), float(heads[v]), mount, max_range, o, relief
            ).reshape(n_beams, n_sub)
            sub_l = np.where(g < sub_r, -1, sub_l)
            sub_r = np.minimum(sub_r, g)
        if n_sub == 1:
            ranges[v] = sub_r[:, 0]
            hit[v] = sub_l[:, 0]
        else:  # the shared footprint model (stemmap.sim.footprint), as the simulator's
            ranges[v] = footprint_ranges(sub_r, energy, min_hit_fraction)
            ok_b = np.isfinite(ranges[v])
            hit[v] = np.where(ok_b, sub_l[np.arange(n_beams), np.argmin(sub_r, axis=1)], -1)
    return ranges, hit


def noisy_batch(
    ranges0: FloatArray, resolution_deg: float, noise: float, rng: np.random.Generator
) -> ScanBatch:
    """The virtual scans ``ranges0`` (V, N) of :func:`virtual_scans` as a ScanBatch, with
    Gaussian range noise of ``noise`` metres per beam (kept >= 5 cm; no return stays inf).

    ``noise == 0`` draws nothing from ``rng``, so later draws from the same generator differ
    from a run with noise > 0. Kept on purpose: the seeded real-slice benchmarks
    (``QUICK_SCANNERS`` / ``FULL_SCANNERS`` put a noise-free level before the noisy ones) and
    ``tests/scan/test_detect_fast_real.py`` depend on this stream."""
    ranges = ranges0 + (rng.normal(0.0, noise, ranges0.shape) if noise > 0 else 0.0)
    ranges = np.where(np.isfinite(ranges0), np.maximum(ranges, 0.05), np.inf)
    return ScanBatch(
        ranges=ranges,
        times=np.arange(ranges0.shape[0], dtype=np.float64),
        angle_min=-math.pi,
        angle_increment=math.radians(resolution_deg),
        range_max=30.0,
    )
