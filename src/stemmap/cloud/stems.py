"""Stem positions and diameters (DBH) from 3D point clouds.

Two methods, both returning a columnar :class:`CloudStems`:

* :func:`detect_stems_munjer` -- EB-LiDAR (Munjer et al. 2025, §3.2-3.3, Table 1): pass-through
  box, voxel-grid averaging, DBSCAN, PCA eccentricity filter, circle fit of the cluster's
  horizontal projection; :func:`associate_proximity` merges detections across frames (1.0 m).
  Preset ``"munjer2025"``.
* :func:`detect_stems` -- ours, for terrestrial, mobile and robot clouds: ground model and height
  normalisation, several horizontal slices around breast height, grid clustering of the
  slice band, robust geometric circle fits per slice (``scan.circle`` "ours", batched) with
  quality tests (arc coverage, residual, point count), a taper/lean line through the slices
  evaluated at 1.3 m, and optional stem height. Every threshold derives from the measured point
  spacing or the measured residual noise floor: no per-cloud tuning. Preset ``"ours"``.
  Clusters with too few points per slice get one pooled tilted-cylinder fit over the band
  (:func:`_pooled_stems`); given each point's sensor position (``origins``), slice fits are
  refined with residuals along the rays (:func:`_refine_along_rays`).

:func:`detect_stems_file` streams a LAS/LAZ file in chunks (two passes: ground, then band), so
a 20-million-point cloud is processed in bounded memory; with
:class:`stemmap.cloud.sensor.SensorPositions` (a station, or a trajectory and the points' time
stamps) it gets the along-ray refinement too.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.cloud.cluster import dbscan
from stemmap.cloud.filters import as_xyz, pass_through, voxel_downsample
from stemmap.cloud.ground import GroundAccumulator, GroundModel
from stemmap.cloud.sensor import SensorPositions
from stemmap.cloud.shape import cluster_covariances, pca_eccentricity
from stemmap.errors import ConfigError, InputError
from stemmap.scan.circle import fit_circles_batch
from stemmap.types import FloatArray, StemObservations

__all__ = [
    "PRESETS",
    "CloudStems",
    "MunjerConfig",
    "StemConfig",
    "associate_proximity",
    "detect_stems",
    "detect_stems_file",
    "detect_stems_munjer",
    "get_preset",
]

log = logging.getLogger(__name__)

BREAST_HEIGHT = 1.3


# --------------------------------------------------------------------------------------------
# result
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class CloudStems:
    """Stems found in one cloud (columnar).

    Attributes
    ----------
    xy : ndarray (K, 2), metres -- stem centre at breast height, cloud frame
    z : ndarray (K,), metres -- z (cloud frame) of the breast-height cross-section
    diameter : ndarray (K,), metres -- DBH
    n_points : ndarray (K,), int -- points supporting the fits
    quality : ndarray (K,), in [0, 1]
    arc_deg : ndarray (K,) -- mean angular coverage of the fitted slices, degrees
    rms : ndarray (K,), metres -- mean residual RMS of the fitted slices
    n_slices : ndarray (K,), int -- slices that passed the quality tests
    taper : ndarray (K,) -- radius change per metre of height (NaN if not estimated)
    height : ndarray (K,), metres -- stem (tree) height, NaN unless requested
    eccentricity : ndarray (K,) -- Munjer's lambda1/lambda2 (NaN for ours)
    method : str
    frame : str
    spacing : float, metres -- measured point spacing (NaN for munjer2025)
    reason : str -- why nothing was found (empty results are falsy)
    """

    xy: FloatArray
    z: FloatArray
    diameter: FloatArray
    n_points: NDArray[np.int64]
    quality: FloatArray
    arc_deg: FloatArray
    rms: FloatArray
    n_slices: NDArray[np.int64]
    taper: FloatArray
    height: FloatArray
    eccentricity: FloatArray
    method: str = ""
    frame: str = "cloud"
    spacing: float = math.nan
    reason: str = ""

    def __len__(self) -> int:
        return int(self.xy.shape[0])

    def __bool__(self) -> bool:
        """False when no stem was found (``reason`` says why)."""
        return len(self) > 0

    @classmethod
    def empty(
        cls, method: str, frame: str = "cloud", spacing: float = math.nan, *, reason: str = ""
    ) -> CloudStems:
        z = np.zeros(0)
        zi = np.zeros(0, dtype=np.int64)
        return cls(np.zeros((0, 2)), z, z, zi, z, z, z, zi, z, z, z, method, frame, spacing, reason)

    @classmethod
    def from_columns(cls, **cols: Any) -> CloudStems:
        k = np.asarray(cols["xy"]).reshape(-1, 2).shape[0]
        nan = np.full(k, np.nan)
        defaults: dict[str, Any] = {
            "quality": np.ones(k),
            "arc_deg": nan,
            "rms": nan,
            "n_slices": np.ones(k, dtype=np.int64),
            "taper": nan,
            "height": nan,
            "eccentricity": nan,
        }
        defaults.update(cols)
        d = defaults
        return cls(
            xy=np.asarray(d["xy"], dtype=np.float64).reshape(-1, 2),
            z=np.asarray(d["z"], dtype=np.float64).reshape(-1),
            diameter=np.asarray(d["diameter"], dtype=np.float64).reshape(-1),
            n_points=np.asarray(d["n_points"], dtype=np.int64).reshape(-1),
            quality=np.asarray(d["quality"], dtype=np.float64).reshape(-1),
            arc_deg=np.asarray(d["arc_deg"], dtype=np.float64).reshape(-1),
            rms=np.asarray(d["rms"], dtype=np.float64).reshape(-1),
            n_slices=np.asarray(d["n_slices"], dtype=np.int64).reshape(-1),
            taper=np.asarray(d["taper"], dtype=np.float64).reshape(-1),
            height=np.asarray(d["height"], dtype=np.float64).reshape(-1),
            eccentricity=np.asarray(d["eccentricity"], dtype=np.float64).reshape(-1),
            method=str(d.get("method", "")),
            frame=str(d.get("frame", "cloud")),
            spacing=float(d.get("spacing", math.nan)),
        )

    def select(self, idx: ArrayLike) -> CloudStems:
        i = np.asarray(idx)
        return replace(
            self,
            **{
                k: getattr(self, k)[i]
                for k in (
                    "xy",
                    "z",
                    "diameter",
                    "n_points",
                    "quality",
                    "arc_deg",
                    "rms",
                    "n_slices",
                    "taper",
                    "height",
                    "eccentricity",
                )
            },
        )

    def to_observations(self, time: float = 0.0, index: int = 0) -> StemObservations:
        """As a :class:`StemObservations` batch (covariance NaN: not estimated per stem)."""
        k = len(self)
        return StemObservations(
            centers=self.xy,
            radii=self.diameter / 2,
            covs=np.full((k, 3, 3), np.nan),
            n_points=self.n_points,
            arc_deg=self.arc_deg,
            widths=np.full(k, np.nan),
            quality=self.quality,
            index=np.full(k, index, dtype=np.int64),
            times=np.full(k, time),
            source=f"cloud:{self.method}",
            frame=self.frame,
        )


# --------------------------------------------------------------------------------------------
# EB-LiDAR (Munjer et al. 2025)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class MunjerConfig:
    """Parameters of EB-LiDAR (Munjer et al. 2025, §3.2-3.3 and Table 1).

    Attributes
    ----------
    box_x, box_y, box_z : (lo, hi), metres, lidar frame
        Pass-through box; the paper: x (0, 10), y (-10, 10), z (-0.5, 0).
    voxel : float, metres -- voxel-grid averaging (0.01)
    eps : float, metres -- DBSCAN neighbourhood radius (0.25)
    min_points : int -- DBSCAN minimum points (20)
    eccentricity_range : (lo, hi) -- kept clusters' lambda1/lambda2 (10, 20)
    fit_std_max : float, metres -- "standard deviation limit for cylinder fitting" (0.1)
    association_distance : float, metres -- proximity association across frames (1.0)
    fit_method : str -- circle fit of the projection (a ``FIT_METHODS`` name; the paper does not
        name one, so the algebraic Kasa fit is the default)
    """

    box_x: tuple[float, float] | None = (0.0, 10.0)
    box_y: tuple[float, float] | None = (-10.0, 10.0)
    box_z: tuple[float, float] | None = (-0.5, 0.0)
    voxel: float = 0.01
    eps: float = 0.25
    min_points: int = 20
    eccentricity_range: tuple[float, float] = (10.0, 20.0)
    fit_std_max: float = 0.1
    association_distance: float = 1.0
    fit_method: str = "kasa"

    def __post_init__(self) -> None:
        if not (self.voxel > 0 and self.eps > 0 and self.min_points >= 1):
            raise ConfigError("munjer2025 needs voxel > 0, eps > 0 and min_points >= 1.")
        lo, hi = self.eccentricity_range
        if not hi >= lo >= 1:
            raise ConfigError(f"eccentricity_range must satisfy 1 <= lo <= hi, got {lo}, {hi}.")


def detect_stems_munjer(xyz: ArrayLike, config: MunjerConfig | None = None) -> CloudStems:
    """EB-LiDAR stem detection in one lidar frame (Munjer et al. 2025, §3.2-3.3).

    Parameters
    ----------
    xyz : array_like (N, 3), metres, lidar frame (x forward, z up, origin at the sensor)
    config : MunjerConfig, default the published Table 1 values

    Returns
    -------
    CloudStems
        One row per accepted cluster: centre and diameter from the circle fit of its xy
        projection, ``z`` its mean height, ``eccentricity`` its lambda1/lambda2.

    Notes
    -----
    Pipeline: pass-through box (§3.2) -> voxel-grid averaging, eq. (2) -> DBSCAN(eps, minPts)
    (§3.3) -> covariance of each cluster, eq. (3), and eccentricity ``e = lambda1 / lambda2``,
    eq. (4), over the two largest eigenvalues of the 3D covariance -> keep ``10 <= e <= 20``
    (§3.3: "between 10 and 20"; Table 1 names 20 the cutoff) -> circle fit of the cluster's 2D
    projection, rejected when the residual standard deviation exceeds 0.1 m (Table 1).
    """
    cfg = config or MunjerConfig()
    p = as_xyz(xyz)
    p = p[pass_through(p, x=cfg.box_x, y=cfg.box_y, z=cfg.box_z)]
    if p.shape[0] < cfg.min_points:
        return CloudStems.empty(
            "munjer2025", reason=f"fewer than {cfg.min_points} points inside the pass-through box"
        )
    v = np.asarray(voxel_downsample(p, cfg.voxel))
    lab = dbscan(v, cfg.eps, cfg.min_points)
    if lab.size == 0 or lab.max() < 0:
        return CloudStems.empty("munjer2025", reason="DBSCAN found no cluster")
    cen, cov, sizes = cluster_covariances(v, lab)
    ecc = pca_eccentricity(cov)
    lo, hi = cfg.eccentricity_range
    cand = np.flatnonzero((ecc >= lo) & (ecc <= hi) & (sizes >= cfg.min_points))
    if cand.size == 0:
        return CloudStems.empty(
            "munjer2025", reason=f"no cluster has an eccentricity in [{lo}, {hi}]"
        )
    sel = np.isin(lab, cand)
    fits = fit_circles_batch(v[sel, :2], lab[sel], cfg.fit_method, edges=None)
    ok = fits.ok & (fits.rms <= cfg.fit_std_max)
    ids = fits.segment_ids[ok]
    return CloudStems.from_columns(
        xy=fits.centers[ok],
        z=cen[ids, 2],
        diameter=2 * fits.radii[ok],
        n_points=sizes[ids],
        rms=fits.rms[ok],
        eccentricity=ecc[ids],
        method="munjer2025",
        frame="lidar",
    )


def associate_proximity(
    detections: Iterable[CloudStems], distance: float = 1.0, *, frame: str = "world"
) -> CloudStems:
    """Merge per-frame detections (already in one common frame) into trees by proximity.

    Munjer et al. (2025, Table 1, "proximity threshold for cluster association", 1.0 m): a
    detection within ``distance`` of an existing tree's running-mean position joins it (the
    nearest), otherwise it starts a new tree. Output positions are the running means, diameters
    the medians of the joined detections, ``n_points`` the summed support and ``n_slices`` the
    number of joined detections.
    """
    if not distance > 0:
        raise ConfigError(f"association distance must be > 0 m, got {distance}.")
    sums: list[FloatArray] = []
    diams: list[list[float]] = []
    zs: list[list[float]] = []
    npts: list[int] = []
    ecc: list[list[float]] = []
    for det in detections:
        for k in range(len(det)):
            c = det.xy[k]
            j = -1
            if sums:
                means = np.array([s[:2] / s[2] for s in sums])
                dist = np.hypot(*(means - c).T)
                m = int(np.argmin(dist))
                j = m if dist[m] <= distance else -1
            if j < 0:
                sums.append(np.array([c[0], c[1], 1.0]))
                diams.append([float(det.diameter[k])])
                zs.append([float(det.z[k])])
                npts.append(int(det.n_points[k]))
                ecc.append([float(det.eccentricity[k])])
            else:
                sums[j] += [c[0], c[1], 1.0]
                diams[j].append(float(det.diameter[k]))
                zs[j].append(float(det.z[k]))
                npts[j] += int(det.n_points[k])
                ecc[j].append(float(det.eccentricity[k]))
    if not sums:
        return CloudStems.empty("munjer2025", frame, reason="no detections to associate")
    s = np.array(sums)
    return CloudStems.from_columns(
        xy=s[:, :2] / s[:, 2:3],
        z=[float(np.mean(v)) for v in zs],
        diameter=[float(np.median(v)) for v in diams],
        n_points=npts,
        n_slices=s[:, 2].astype(np.int64),
        eccentricity=[float(np.median(v)) for v in ecc],
        method="munjer2025",
        frame=frame,
    )


# --------------------------------------------------------------------------------------------
# ours
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class StemConfig:
    """Parameters of our stem detector. Defaults need no per-cloud tuning.

    Attributes
    ----------
    breast_height : float, metres (1.3)
    slice_centers : tuple of float, metres above ground
        Centres of the horizontal slices fitted per stem; the band they span is clustered.
    slice_thickness : float, metres
    ground_cell : float, metres -- ground raster cell (1.0)
    min_diameter, max_diameter : float, metres -- plausible DBH window (0.04, 1.5)
    min_arc_deg : float -- minimum angular coverage of a slice fit (one side of a trunk seen
        from one scanner covers up to ~180 degrees; 30 keeps partly occluded trunks, whose
        DBH is then less certain and whose quality is scaled by arc / 120 degrees)
    min_slice_points : int -- minimum inliers of a slice fit
    min_slices : int -- slices that must pass for a stem (1 for a pre-cut slice cloud)
    min_vertical_extent : float, metres -- the passing slices' centres must span at least this
        (a stem is vertical; bushes and branch stubs are not); ignored for a pre-cut slice
    slices_per_spacing : float -- a slice is at least this many measured point spacings thick;
        sparse clouds get fewer, thicker slices over the same band (0 disables)
    max_taper : float -- largest plausible |d radius / d height| in the band, m/m; a candidate
        whose slice radii change faster is not a stem
    residual_factor : float -- a slice fit passes if its RMS is below ``residual_factor`` times
        the cloud's noise floor (median slice RMS) -- measured, not tuned
    cluster_cell_factor : float -- grid clustering cell = this x the 90th-percentile 2D point
        spacing in the band (measured)
    spacing : float, optional -- override the measured point spacing, metres
    fit_method : str -- circle fit (``scan.circle.FIT_METHODS``); "ours" is the robust
        geometric fit
    estimate_height : bool -- also estimate stem height (highest point within 1 m of the axis)
    slice_mode : "auto" | "always" | "never" -- treat the cloud as an already cut, height-
        normalised slice (auto: when its z extent is below 1 m)
    pooled_fallback : bool -- clusters the per-slice fits reject get one tilted-cylinder fit
        over the whole band with stricter tests (:func:`_pooled_stems`): trunks with few
        returns per slice (partly occluded, sparse clouds)
    """

    breast_height: float = BREAST_HEIGHT
    slice_centers: tuple[float, ...] = (0.9, 1.1, 1.3, 1.5, 1.7, 1.9)
    slice_thickness: float = 0.2
    ground_cell: float = 1.0
    min_diameter: float = 0.04
    max_diameter: float = 1.5
    min_arc_deg: float = 30.0
    min_slice_points: int = 8
    min_slices: int = 3
    residual_factor: float = 3.0
    cluster_cell_factor: float = 2.0
    spacing: float | None = None
    fit_method: str = "ours"
    estimate_height: bool = False
    slice_mode: str = "auto"
    min_vertical_extent: float = 0.4
    slices_per_spacing: float = 4.0
    max_taper: float = 0.05
    pooled_fallback: bool = True

    def __post_init__(self) -> None:
        if not self.slice_centers or self.slice_thickness <= 0:
            raise ConfigError("need at least one slice centre and slice_thickness > 0 m.")
        if not 0 < self.min_diameter < self.max_diameter:
            raise ConfigError(
                f"need 0 < min_diameter < max_diameter, got {self.min_diameter}, "
                f"{self.max_diameter}."
            )
        if self.slice_mode not in ("auto", "always", "never"):
            raise ConfigError(f"slice_mode must be auto, always or never, got {self.slice_mode!r}.")
        if self.spacing is not None and not self.spacing > 0:
            raise ConfigError(f"spacing must be > 0 m, got {self.spacing}.")

    @property
    def band(self) -> tuple[float, float]:
        c = np.asarray(self.slice_centers)
        return float(c.min() - self.slice_thickness / 2), float(c.max() + self.slice_thickness / 2)


PRESETS: dict[str, MunjerConfig | StemConfig] = {
    "munjer2025": MunjerConfig(),
    "ours": StemConfig(),
    "ours_kasa": StemConfig(fit_method="kasa"),
}


def get_preset(name: str) -> MunjerConfig | StemConfig:
    """A named configuration (``"munjer2025"``, ``"ours"``, ``"ours_kasa"``)."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ConfigError(
            f"unknown stems preset {name!r}; choose one of {sorted(PRESETS)}."
        ) from None


@dataclass
class _Band:
    """Points of the slice band: xy, height above ground, absolute z; a canopy raster; and
    optionally each point's sensor position (xy)."""

    xy: FloatArray
    h: FloatArray
    z: FloatArray
    canopy: dict[str, Any] = field(default_factory=dict)
    origins: FloatArray | None = None  # (N, 2) horizontal sensor position of each point


def _slice_setup(cfg: StemConfig, zmin: float, zmax: float, slice_mode: bool) -> StemConfig:
    if not slice_mode:
        return cfg
    # a pre-cut slice: split its extent into sub-slices of >= 5 cm, at most 3
    ext = max(zmax - zmin, 1e-3)
    n = int(np.clip(ext // 0.05, 1, 3))
    th = ext / n
    centers = tuple(float(zmin + th * (k + 0.5)) for k in range(n))
    return replace(
        cfg,
        slice_centers=centers,
        slice_thickness=th * 1.0001,
        min_slices=1,
        breast_height=float((zmin + zmax) / 2),
    )


def detect_stems(
    xyz: ArrayLike,
    config: StemConfig | None = None,
    *,
    ground: GroundModel | None = None,
    origins: ArrayLike | None = None,
) -> CloudStems:
    """Our stem detector on an in-memory cloud (see the module docstring).

    Parameters
    ----------
    xyz : array_like (N, 3), metres
        Any frame with z up. Clouds whose z extent is below 1 m are taken as already
        height-normalised slices (``config.slice_mode``).
    config : StemConfig, default preset "ours"
    ground : GroundModel, optional
        Use this ground instead of fitting one.
    origins : array_like (N, 3) or (3,), metres, optional
        Sensor position of each point (a TLS station; for a mobile cloud the trajectory pose
        at the point's time). When given, the slice fits are refined with residuals along the
        rays (:func:`_refine_along_rays`): range noise lies along the ray, not across the
        surface, which biases orthogonal-distance fits of one-sided arcs low. Only the
        geometric fit uses them: with ``fit_method="kasa"`` they raise a ConfigError rather
        than being silently ignored.

    Returns
    -------
    CloudStems
        ``z`` is the absolute z of breast height at each stem; ``quality`` combines the
        fraction of slices passing, their arc coverage and residual.
    """
    cfg = config or StemConfig()
    p = as_xyz(xyz)
    if p.shape[0] == 0:
        return CloudStems.empty("ours", reason="the cloud is empty")
    o: FloatArray | None = None
    if origins is not None:
        if cfg.fit_method == "kasa":
            raise ConfigError(
                "origins are used only by the geometric fit (preset 'ours'); the Kasa fit has "
                "no along-ray refinement. Drop origins or use fit_method='ours'."
            )
        o = np.asarray(origins, dtype=np.float64)
        if o.shape == (3,) or o.shape == (2,):
            o = np.broadcast_to(o[:2], (p.shape[0], 2))
        elif o.ndim == 2 and o.shape[0] == p.shape[0] and o.shape[1] in (2, 3):
            o = o[:, :2]
        else:
            raise InputError(
                f"origins must have shape (3,) or (N, 3) with N = {p.shape[0]}, got {o.shape}."
            )
        if not np.all(np.isfinite(o)):
            raise InputError("origins hold non-finite values.")
    zmin, zmax = float(p[:, 2].min()), float(p[:, 2].max())
    is_slice = cfg.slice_mode == "always" or (cfg.slice_mode == "auto" and zmax - zmin < 1.0)
    cfg = _slice_setup(cfg, zmin, zmax, is_slice)
    if is_slice:
        band = _Band(p[:, :2], p[:, 2], p[:, 2], origins=o)
    else:
        g = ground or _ground_of([p], cfg.ground_cell)
        h = g.height_of(p)
        lo, hi = cfg.band
        m = (h >= lo) & (h <= hi)
        band = _Band(p[m, :2], h[m], p[m, 2], origins=None if o is None else o[m])
        if cfg.estimate_height:
            band.canopy = _canopy_update({}, p[:, :2], h)
    return _stems_from_band(band, cfg, slice_cloud=is_slice)


def _ground_of(chunks: Iterable[FloatArray], cell: float) -> GroundModel:
    acc = GroundAccumulator(cell)
    for c in chunks:
        acc.update(c)
    return acc.model()


_CANOPY_CELL = 0.25
_KEY_OFF = 1 << 30


def _canopy_update(canopy: dict[str, Any], xy: FloatArray, h: FloatArray) -> dict[str, Any]:
    """Running max height per 0.25 m cell (keys -> max h), for stem height."""
    if xy.shape[0] == 0:
        return canopy
    ij = np.floor(xy / _CANOPY_CELL).astype(np.int64) + _KEY_OFF
    keys = (ij[:, 0] << 32) | ij[:, 1]
    if canopy:
        keys = np.concatenate((canopy["keys"], keys))
        h = np.concatenate((canopy["h"], h))
    order = np.lexsort((-h, keys))
    keys, h = keys[order], h[order]
    first = np.ones(keys.shape[0], dtype=bool)
    first[1:] = keys[1:] != keys[:-1]
    return {"keys": keys[first], "h": h[first]}


def _stem_heights(canopy: dict[str, Any], xy: FloatArray, radius: float = 1.0) -> FloatArray:
    if not canopy:
        return np.full(xy.shape[0], np.nan)
    i = (canopy["keys"] >> 32) - _KEY_OFF
    j = (canopy["keys"] & 0xFFFFFFFF) - _KEY_OFF
    cxy = (np.column_stack((i, j)) + 0.5) * _CANOPY_CELL
    from scipy.spatial import cKDTree

    tree = cKDTree(cxy)
    out = np.full(xy.shape[0], np.nan)
    for k, nb in enumerate(tree.query_ball_point(xy, radius)):
        if nb:
            out[k] = float(np.max(canopy["h"][nb]))
    return out


def _band_spacing(xy: FloatArray, h: FloatArray, rng: int = 0) -> float:
    """90th percentile of the 3D nearest-neighbour distance of band points (sampled).

    3D, not in the xy projection: a scanner's rows stack on a trunk, so projected neighbours
    are much closer than neighbours along the arc, which is what clustering must bridge. The
    90th percentile (not the median) speaks for the sparse, far trunks.
    """
    from scipy.spatial import cKDTree

    n = xy.shape[0]
    if n < 3:
        return math.nan
    p = np.column_stack((xy, h))
    gen = np.random.default_rng(rng)
    q = p if n <= 20_000 else p[gen.choice(n, 20_000, replace=False)]
    d, _ = cKDTree(p).query(q, k=2)
    d = d[:, 1]
    d = d[d > 1e-9]
    return float(np.quantile(d, 0.9)) if d.size else math.nan


def _far_origins(
    pts: FloatArray, ids: NDArray[np.int64], k: int, centers: FloatArray
) -> FloatArray:
    """A viewpoint far out on the visible side of each segment (for the geometric fit's
    'centre behind the arc' test): centre + 1 km along (points' centroid - centre)."""
    cnt = np.maximum(np.bincount(ids, minlength=k), 1)
    cen = np.column_stack([np.bincount(ids, pts[:, j], k) / cnt for j in range(2)])
    d = cen - centers
    norm = np.hypot(d[:, 0], d[:, 1])
    d = np.where(norm[:, None] > 1e-6, d / np.maximum(norm, 1e-12)[:, None], [1.0, 0.0])
    c = np.where(np.isfinite(centers), centers, cen)
    return np.asarray(c + 1000.0 * d, dtype=np.float64)


def _segment_arcs(
    pts: FloatArray, ids: NDArray[np.int64], k: int, centers: FloatArray
) -> FloatArray:
    """Arc coverage (degrees) of every segment around its centre, vectorised."""
    a = np.arctan2(pts[:, 1] - centers[ids, 1], pts[:, 0] - centers[ids, 0])
    order = np.lexsort((a, ids))
    a, s = a[order], ids[order]
    nxt = np.roll(a, -1)
    first = np.ones(s.shape[0], dtype=bool)
    first[1:] = s[1:] != s[:-1]
    last = np.roll(first, -1)
    # wrap: the gap after a segment's last angle goes to its first angle + 2 pi
    first_angle = a[first]
    seg_of_first = s[first]
    wrap_to = np.empty(k)
    wrap_to[seg_of_first] = first_angle + 2 * np.pi
    gap = np.where(last, wrap_to[s] - a, nxt - a)
    maxgap = np.zeros(k)
    np.maximum.at(maxgap, s, gap)
    cnt = np.bincount(ids, minlength=k)
    arc = np.degrees(2 * np.pi - maxgap)
    return np.asarray(np.where(cnt >= 2, arc, 0.0), dtype=np.float64)


def _ransac_circle(
    q: FloatArray,
    tol: float,
    radius_window: tuple[float, float],
    gen: np.random.Generator,
    n_hyp: int = 96,
) -> tuple[float, float, float] | None:
    """Circle through 3 random points with the most points within ``tol``, vectorised over
    ``n_hyp`` hypotheses; None if no hypothesis has a radius inside ``radius_window``."""
    m = q.shape[0]
    if m < 3:
        return None
    t = gen.integers(0, m, (n_hyp, 3))
    a, b, c = q[t[:, 0]], q[t[:, 1]], q[t[:, 2]]
    d = 2 * (
        a[:, 0] * (b[:, 1] - c[:, 1])
        + b[:, 0] * (c[:, 1] - a[:, 1])
        + c[:, 0] * (a[:, 1] - b[:, 1])
    )
    good = np.abs(d) > 1e-12
    if not good.any():
        return None
    a, b, c, d = a[good], b[good], c[good], d[good]
    a2, b2, c2 = (a * a).sum(1), (b * b).sum(1), (c * c).sum(1)
    ux = (a2 * (b[:, 1] - c[:, 1]) + b2 * (c[:, 1] - a[:, 1]) + c2 * (a[:, 1] - b[:, 1])) / d
    uy = (a2 * (c[:, 0] - b[:, 0]) + b2 * (a[:, 0] - c[:, 0]) + c2 * (b[:, 0] - a[:, 0])) / d
    r = np.hypot(a[:, 0] - ux, a[:, 1] - uy)
    inwin = (r >= radius_window[0]) & (r <= radius_window[1])
    if not inwin.any():
        return None
    ux, uy, r = ux[inwin], uy[inwin], r[inwin]
    res = np.abs(np.hypot(q[None, :, 0] - ux[:, None], q[None, :, 1] - uy[:, None]) - r[:, None])
    score = (res <= tol).sum(axis=1)
    j = int(np.argmax(score))
    return float(ux[j]), float(uy[j]), float(r[j])


def _fit_segments(
    pts: FloatArray,
    ids: NDArray[np.int64],
    k: int,
    method: str,
    *,
    ransac_tol: float = 0.0,
    radius_window: tuple[float, float] = (0.0, np.inf),
    ray_origins: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_], NDArray[np.int64]]:
    """Robust batched circle fit of K segments: fit, trim |res| > 3 sigma (MAD), refit.

    With ``ray_origins`` (N, 2: each point's sensor position) the result is refined with
    residuals along the rays (:func:`_refine_along_rays`). Returns centres (K, 2), radii,
    rms, ok, inlier counts; rows for ids absent from ``ids`` are NaN / False.
    """
    centers = np.full((k, 2), np.nan)
    radii = np.full(k, np.nan)
    rms = np.full(k, np.nan)
    ok = np.zeros(k, dtype=bool)
    nin = np.zeros(k, dtype=np.int64)
    if pts.shape[0] == 0:
        return centers, radii, rms, ok, nin
    first = fit_circles_batch(pts, ids, "kasa")
    c0 = np.full((k, 2), np.nan)
    c0[first.segment_ids] = first.centers
    keep = np.ones(pts.shape[0], dtype=bool)
    # segments the algebraic fit explains badly (a branch or a bush glued to the trunk): find
    # the dominant circle by RANSAC first and start from its inliers
    suspect = ~first.ok | (first.rms > 0.05 * np.where(first.ok, first.radii, 1.0))
    if suspect.any() and ransac_tol > 0:
        order = np.argsort(ids, kind="stable")
        starts = np.searchsorted(ids[order], first.segment_ids)
        stops = np.searchsorted(ids[order], first.segment_ids, side="right")
        gen = np.random.default_rng(0)
        for row in np.flatnonzero(suspect)[:2000]:
            idx = order[starts[row] : stops[row]]
            best = _ransac_circle(pts[idx], ransac_tol, radius_window, gen)
            if best is None:
                continue
            cx, cy, r = best
            res = np.abs(np.hypot(pts[idx, 0] - cx, pts[idx, 1] - cy) - r)
            keep[idx] = res <= 3 * ransac_tol
            c0[first.segment_ids[row]] = (cx, cy)
    for it in range(2):
        sel_ids = ids[keep]
        present = np.unique(sel_ids)
        if present.size == 0:
            break
        if method == "kasa":
            fits = fit_circles_batch(pts[keep], sel_ids, "kasa")
        else:
            origins = _far_origins(pts[keep], sel_ids, k, c0)[present]
            fits = fit_circles_batch(
                pts[keep],
                sel_ids,
                method,
                origin=origins,
                edges=np.zeros((present.size, 2), dtype=bool),
            )
        centers[:] = np.nan
        radii[:] = np.nan
        ok[:] = False
        centers[fits.segment_ids] = fits.centers
        radii[fits.segment_ids] = fits.radii
        ok[fits.segment_ids] = fits.ok
        c0 = np.where(np.isfinite(centers), centers, c0)
        if it == 1:
            break
        # trim outliers: |residual| > max(3 * 1.4826 * MAD, 1 mm) of the segment
        good = ok[ids]
        res = np.full(pts.shape[0], np.inf)
        res[good] = np.abs(np.hypot(*(pts[good] - centers[ids[good]]).T) - radii[ids[good]])
        mad = np.full(k, np.inf)
        for_seg = np.flatnonzero(good)
        if for_seg.size:
            order = np.lexsort((res[for_seg], ids[for_seg]))
            s_ids = ids[for_seg][order]
            s_res = res[for_seg][order]
            starts = np.flatnonzero(np.r_[True, s_ids[1:] != s_ids[:-1]])
            counts = np.diff(np.r_[starts, s_ids.size])
            med = s_res[starts + counts // 2]
            mad[s_ids[starts]] = med
        thr = np.maximum(3.0 * 1.4826 * mad, 0.001)
        keep = good & (res <= thr[ids])
        keep |= ~good  # segments that failed keep their points for the second try
    if ray_origins is not None and method != "kasa":
        sel = ok[ids] & keep
        wide = ok & (
            _segment_arcs(pts[sel], ids[sel], k, np.where(ok[:, None], centers, 0))
            >= RAY_MIN_ARC_DEG
        )
        sel &= wide[ids]
        centers, radii = _refine_along_rays(
            pts[sel], ids[sel], ray_origins[sel], k, centers, radii, wide
        )
    res2 = np.full(pts.shape[0], np.nan)
    good = ok[ids] & keep
    res2[good] = np.hypot(*(pts[good] - centers[ids[good]]).T) - radii[ids[good]]
    nin = np.bincount(ids[good], minlength=k).astype(np.int64)
    ss = np.bincount(ids[good], res2[good] ** 2, minlength=k)
    rms = np.sqrt(ss / np.maximum(nin, 1))
    rms = np.where(nin > 0, rms, np.nan)
    return centers, radii, rms, ok, nin


RAY_MIN_COS = 0.5
RAY_MIN_ARC_DEG = 90.0


def _range_errors(
    pts: FloatArray, ids: NDArray[np.int64], u: FloatArray, c: FloatArray, r: FloatArray
) -> FloatArray:
    """Range error of each point along its (horizontal, unit) ray ``u`` for circles (c, r).

    The ray enters the circle at ``p - e u`` with ``|p - e u - c| = r``; the entry nearest the
    sensor is ``e = w.u + sqrt((w.u)^2 - |w|^2 + r^2)``, ``w = p - c`` (exact, any incidence).
    Rays that miss the circle (negative discriminant: grazing returns pushed outside by noise)
    get the orthogonal residual scaled as at a 60-degree incidence, ``d / RAY_MIN_COS`` (0.5;
    a heuristic: beyond the tangent no range error reaches the circle).
    """
    w = pts - c[ids]
    wu = np.sum(w * u, axis=1)
    ww = np.sum(w * w, axis=1)
    disc = wu * wu - ww + r[ids] ** 2
    d = np.sqrt(ww) - r[ids]
    return np.asarray(
        np.where(disc >= 0, wu + np.sqrt(np.maximum(disc, 0.0)), d / RAY_MIN_COS),
        dtype=np.float64,
    )


def _refine_along_rays(
    pts: FloatArray,
    ids: NDArray[np.int64],
    origins: FloatArray,
    k: int,
    centers: FloatArray,
    radii: FloatArray,
    ok: NDArray[np.bool_],
    n_iter: int = 10,
) -> tuple[FloatArray, FloatArray]:
    """Refine circle fits by minimising each point's range error along its ray.

    A lidar's range noise lies along the ray. The orthogonal distance of a point to the
    circle is then about ``eps cos(alpha)`` (alpha: incidence angle between the horizontal
    ray and the surface normal): full on the front of a one-sided arc, small on its flanks,
    where the noise moves returns along the surface and, at grazing incidence, outside it. An
    orthogonal-distance fit treats all returns alike and shrinks the radius of one-sided arcs
    (2D Monte Carlo, r = 14 cm, half arc, 3 cm noise along one view direction: -0.7 to -0.9 cm
    of DBH; radial noise: none; docs/algorithms/cloud.md, Known limits). The maximum-likelihood
    fit under range noise minimises the range errors themselves (:func:`_range_errors`,
    exact at any incidence). Batched damped Gauss-Newton over (cx, cy, r) of all segments,
    finite-difference Jacobian (the exact residual's derivative is singular at tangency),
    soft-L1 weights with a scale of 3 x the segment's orthogonal RMS (about 2.5 range-noise
    sigmas), 10 iterations from the orthogonal fit. Segments whose step fails keep their
    current fit. The caller refines only arcs of at least ``RAY_MIN_ARC_DEG`` (90): on
    narrower arcs the radius is ill-conditioned (sagitta < 30 % of r) and its random error,
    not this bias, dominates (a 28-56 degree trunk of the terrestrial benchmark moved by
    3.5 cm with the first-order variant).
    """
    c = centers.copy()
    r = radii.copy()
    if pts.shape[0] == 0:
        return c, r
    u = pts - origins
    u = u / np.maximum(np.hypot(u[:, 0], u[:, 1]), 1e-9)[:, None]
    cnt = np.bincount(ids, minlength=k)
    d0 = np.hypot(*(pts - c[ids]).T) - r[ids]
    rms0 = np.sqrt(np.bincount(ids, d0 * d0, minlength=k) / np.maximum(cnt, 1))
    f = np.maximum(3.0 * rms0, 1e-3)[ids]
    hstep = 1e-6
    for _ in range(n_iter):
        e = _range_errors(pts, ids, u, c, r)
        w = 1.0 / np.sqrt(1.0 + (e / f) ** 2)  # soft-L1 (IRLS)
        J = np.empty((pts.shape[0], 3))
        for j in range(3):
            cc, rr = c.copy(), r.copy()
            if j < 2:
                cc[:, j] += hstep
            else:
                rr += hstep
            J[:, j] = (_range_errors(pts, ids, u, cc, rr) - e) / hstep
        A = np.zeros((k, 3, 3))
        g = np.zeros((k, 3))
        for a in range(3):
            g[:, a] = np.bincount(ids, w * J[:, a] * e, minlength=k)
            for b in range(a, 3):
                A[:, a, b] = A[:, b, a] = np.bincount(ids, w * J[:, a] * J[:, b], minlength=k)
        A += 1e-3 * np.einsum("kii->ki", A)[:, :, None] * np.eye(3)[None] + 1e-12 * np.eye(3)
        good = ok & (cnt >= 3)
        if not good.any():
            break
        step = np.zeros((k, 3))
        step[good] = np.linalg.solve(A[good], -g[good][:, :, None])[:, :, 0]
        r_new = r + step[:, 2]
        good &= (
            np.isfinite(step).all(axis=1)
            & (r_new > 0)
            & (np.abs(step[:, 2]) < 0.5 * np.maximum(r, 1e-3))
        )
        c = np.where(good[:, None], c + step[:, :2], c)
        r = np.where(good, r_new, r)
    return c, r


def _adapt_slices(cfg: StemConfig, spacing: float) -> StemConfig:
    """Thicker, fewer slices over the same band when the cloud is sparse.

    A slice must be at least ``slices_per_spacing`` point spacings thick so that a trunk side
    holds enough points for a fit; the band (first to last slice edge) is kept and cut into as
    many equal slices of at least that thickness as fit, never fewer than 3.
    """
    lo, hi = cfg.band
    need = max(cfg.slice_thickness, cfg.slices_per_spacing * spacing)
    if need <= cfg.slice_thickness + 1e-12:
        return cfg
    n = max(3, int((hi - lo) // need))
    th = (hi - lo) / n
    centers = tuple(float(lo + th * (k + 0.5)) for k in range(n))
    log.info("sparse cloud (spacing %.3f m): %d slices of %.2f m", spacing, n, th)
    return replace(cfg, slice_centers=centers, slice_thickness=th)


def _theil_sen(x: FloatArray, y: FloatArray) -> tuple[float, float]:
    """Theil-Sen line ``y = a + b x``: b the median pairwise slope, a the median intercept."""
    i, j = np.triu_indices(x.size, 1)
    dx = x[j] - x[i]
    ok = np.abs(dx) > 1e-9
    b = float(np.median((y[j] - y[i])[ok] / dx[ok])) if ok.any() else 0.0
    return float(np.median(y - b * x)), b


def _vertical_filter(
    xy: FloatArray, sl: NDArray[np.int64], ns: int, cell: float
) -> NDArray[np.bool_]:
    """Keep points whose 2D cell is occupied in at least half of the slices (>= 2).

    A trunk's surface projects onto the same cells at every height of the band; branches,
    needles and leaves occupy a cell at one or two heights only. Removing them before
    clustering keeps them out of the circle fits (a spruce whorl otherwise swamps its stem).
    The cell (3-10 cm) tolerates the lean of a stem between adjacent slices.
    """
    ij = np.floor((xy - xy.min(axis=0)) / cell).astype(np.int64)
    ny = int(ij[:, 1].max()) + 1
    key = ij[:, 0] * ny + ij[:, 1]
    ok = sl >= 0
    pair = np.unique(key[ok] * ns + sl[ok])
    cell_keys, n_sl = np.unique(pair // ns, return_counts=True)
    need = max(2, (ns + 1) // 2)
    good_cells = cell_keys[n_sl >= need]
    return np.asarray(ok & np.isin(key, good_cells), dtype=bool)


def _stems_from_band(band: _Band, cfg: StemConfig, *, slice_cloud: bool = False) -> CloudStems:
    xy, h = band.xy, band.h
    n = xy.shape[0]
    if n < cfg.min_slice_points:
        return CloudStems.empty(
            "ours", reason=f"fewer than {cfg.min_slice_points} points in the slice band"
        )
    # --- spacing -> clustering cell (measured, not tuned)
    sp2d = cfg.spacing if cfg.spacing is not None else _band_spacing(xy, h)
    if not math.isfinite(sp2d):
        return CloudStems.empty(
            "ours", reason="point spacing could not be measured (duplicate points only?)"
        )
    cell = float(np.clip(cfg.cluster_cell_factor * sp2d, 0.01, 0.25))
    if not slice_cloud and cfg.slices_per_spacing > 0:
        cfg = _adapt_slices(cfg, sp2d)
    centers_h = np.asarray(cfg.slice_centers, dtype=np.float64)
    ns = centers_h.shape[0]
    # --- slice of each point: the nearest slice centre within half a thickness
    near = np.argmin(np.abs(h[:, None] - centers_h[None, :]), axis=1)
    sl_all = np.where(np.abs(h - centers_h[near]) <= cfg.slice_thickness / 2, near, -1)
    keep = sl_all >= 0
    if not slice_cloud and ns >= 3:
        keep &= _vertical_filter(xy, sl_all, ns, float(np.clip(cell, 0.03, 0.1)))
    xy, h = xy[keep], h[keep]
    sl_all = sl_all[keep]
    orig = None if band.origins is None else band.origins[keep]
    if xy.shape[0] < cfg.min_slice_points:
        return CloudStems.empty(
            "ours", spacing=sp2d, reason="no points left after the vertical-consistency filter"
        )
    # --- grid components with one-cell gap bridging (dilated occupancy)
    from scipy import ndimage

    lo = xy.min(axis=0)
    ij = np.floor((xy - lo) / cell).astype(np.int64)
    shape = ij.max(axis=0) + 1
    if int(shape[0]) * int(shape[1]) > 300_000_000:
        raise InputError(
            f"the slice band spans {shape[0] * cell:.0f} x {shape[1] * cell:.0f} m at a "
            f"{cell:.3f} m clustering cell; tile the cloud into smaller plots."
        )
    flat = ij[:, 0] * shape[1] + ij[:, 1]
    occ = np.zeros(int(shape[0]) * int(shape[1]), dtype=bool)
    occ[flat] = True
    occ2 = occ.reshape(int(shape[0]), int(shape[1]))
    dil = ndimage.binary_dilation(occ2, structure=np.ones((3, 3), bool))
    lab_img, n_lab = ndimage.label(dil, structure=np.ones((3, 3), bool))
    lab = lab_img.ravel()[flat].astype(np.int64) - 1
    # --- candidate clusters: enough points, plausible footprint
    counts = np.bincount(lab, minlength=n_lab)
    xmin = np.full(n_lab, np.inf)
    xmax = np.full(n_lab, -np.inf)
    ymin = np.full(n_lab, np.inf)
    ymax = np.full(n_lab, -np.inf)
    np.minimum.at(xmin, lab, xy[:, 0])
    np.maximum.at(xmax, lab, xy[:, 0])
    np.minimum.at(ymin, lab, xy[:, 1])
    np.maximum.at(ymax, lab, xy[:, 1])
    extent = np.maximum(xmax - xmin, ymax - ymin)
    # a stem's footprint can be widened by an attached branch or shrub in some slices (the
    # per-slice robust fits and consistency tests deal with those), so only absurd ones go
    cand = (counts >= cfg.min_slice_points) & (extent <= 3.0 * cfg.max_diameter + 2 * cell)
    sl = sl_all
    use = cand[lab] & (sl >= 0)
    if not use.any():
        return CloudStems.empty(
            "ours", spacing=sp2d, reason="no cluster has enough points in any slice"
        )
    cl_ids, cl_inv = np.unique(lab[use], return_inverse=True)
    kc = cl_ids.shape[0]
    seg = cl_inv.astype(np.int64) * ns + sl[use]
    pts = xy[use]
    kseg = kc * ns
    seg_n = np.bincount(seg, minlength=kseg)
    fitmask = seg_n[seg] >= cfg.min_slice_points
    pts_f, seg_f = pts[fitmask], seg[fitmask]
    centers, radii, rms, ok, nin = _fit_segments(
        pts_f,
        seg_f,
        kseg,
        cfg.fit_method,
        ransac_tol=max(0.5 * sp2d, 0.005),
        radius_window=(cfg.min_diameter / 2, cfg.max_diameter / 2),
        ray_origins=None if orig is None else orig[use][fitmask],
    )
    arcs = np.zeros(kseg)
    if ok.any():
        good = ok[seg_f]
        arcs = _segment_arcs(pts_f[good], seg_f[good], kseg, np.where(ok[:, None], centers, 0))
    # --- quality tests; noise floor measured from the data
    plausible = (
        ok
        & (nin >= cfg.min_slice_points)
        & (radii >= cfg.min_diameter / 2)
        & (radii <= cfg.max_diameter / 2)
        & (arcs >= cfg.min_arc_deg)
    )
    if not plausible.any():
        return CloudStems.empty(
            "ours",
            spacing=sp2d,
            reason="no slice fit passed the quality tests (points, radius, arc)",
        )
    noise_floor = float(np.median(rms[plausible]))
    rms_max = cfg.residual_factor * max(noise_floor, 0.5 * sp2d / 10, 1e-4)
    passed = plausible & (rms <= np.maximum(rms_max, 0.02 * radii))
    log.debug(
        "slice fits: %d ok, %d enough points, %d radius window, %d arc, %d residual of %d",
        ok.sum(),
        (ok & (nin >= cfg.min_slice_points)).sum(),
        (ok & (radii >= cfg.min_diameter / 2) & (radii <= cfg.max_diameter / 2)).sum(),
        (ok & (arcs >= cfg.min_arc_deg)).sum(),
        passed.sum(),
        ok.size,
    )
    P = passed.reshape(kc, ns)
    C = centers.reshape(kc, ns, 2)
    R = radii.reshape(kc, ns)
    W = (nin / np.maximum(rms, 1e-4) ** 2).reshape(kc, ns)
    A = arcs.reshape(kc, ns)
    RMS = rms.reshape(kc, ns)
    NIN = nin.reshape(kc, ns)
    present = (seg_n.reshape(kc, ns) >= cfg.min_slice_points).sum(axis=1)
    rows: list[tuple[float, ...]] = []
    accepted = np.zeros(kc, dtype=bool)
    for c in np.flatnonzero(P.sum(axis=1) >= cfg.min_slices):
        m = P[c]
        # consistency: drop slices whose radius or centre is far from the median
        r_med = float(np.median(R[c, m]))
        c_med = np.median(C[c, m], axis=0)
        # tolerance: 15 % of the radius, or 5 sigma of a slice radius, whichever is larger.
        # sigma_r is the fit's parameter noise, not the points': ~2 rms / sqrt(n) on a half
        # arc, growing like (180 deg / arc)^2 on shorter arcs (partly occluded trunks)
        short = np.maximum(1.0, 180.0 / np.maximum(A[c, m], 1.0)) ** 2
        sig_r = float(np.median(2.0 * RMS[c, m] / np.sqrt(np.maximum(NIN[c, m], 1)) * short))
        tol = max(0.15 * r_med, 5.0 * sig_r)
        # centres are compared with a robust line through them (a leaning stem's centre
        # moves with height), radii with their median
        if m.sum() >= 3:
            hm = centers_h[m]
            lx, ly = _theil_sen(hm, C[c, m, 0]), _theil_sen(hm, C[c, m, 1])
            pred = np.column_stack((lx[0] + lx[1] * centers_h, ly[0] + ly[1] * centers_h))
        else:
            pred = np.broadcast_to(c_med, C[c].shape)
        m = (
            m
            & (np.abs(R[c] - r_med) <= tol)
            & (np.hypot(*(C[c] - pred).T) <= max(tol, 0.3 * r_med))
        )
        if m.sum() < cfg.min_slices:
            continue
        if not slice_cloud and np.ptp(centers_h[m]) < cfg.min_vertical_extent - 1e-9:
            continue  # not a vertical structure (a bush, a boulder, a branch stub)
        hh = centers_h[m] - cfg.breast_height
        w = W[c, m]
        if m.sum() >= 3 and np.ptp(hh) >= 0.3:
            # robust (Theil-Sen) line through the slices (taper, lean), at breast height: one
            # slice spoilt by a branch or a shrub does not tilt it
            coef_r = _theil_sen(hh, R[c, m])
            coef_x = _theil_sen(hh, C[c, m, 0])
            coef_y = _theil_sen(hh, C[c, m, 1])
            taper = float(coef_r[1])
            if abs(taper) > cfg.max_taper:
                continue  # radius changes too fast with height for a stem (bush, boulder)
            r_bh = float(coef_r[0])
            cxy = np.array([coef_x[0], coef_y[0]])
        else:
            r_bh = float(np.average(R[c, m], weights=w))
            cxy = np.average(C[c, m], axis=0, weights=w)
            taper = math.nan
        frac = float(m.sum()) / max(int(present[c]), 1)
        arc = float(np.mean(A[c, m]))
        rr = float(np.mean(RMS[c, m]))
        q = frac * min(1.0, arc / 120.0) * min(1.0, noise_floor / max(rr, 1e-6))
        rows.append(
            (cxy[0], cxy[1], 2 * r_bh, int(NIN[c, m].sum()), q, arc, rr, int(m.sum()), taper)
        )
        accepted[c] = True
    if cfg.pooled_fallback and not slice_cloud:
        pooled = _pooled_stems(
            pts,
            h[use],
            cl_inv.astype(np.int64),
            sl[use],
            ~accepted & (present < cfg.min_slices),  # too few points per slice
            cfg,
            centers_h,
            noise_floor,
        )
        if pooled:
            log.info("%d stem(s) from the pooled band fit", len(pooled))
            rows.extend(pooled)
    if not rows:
        return CloudStems.empty(
            "ours",
            spacing=sp2d,
            reason="no cluster passed the per-stem tests (slices, vertical extent, taper)",
        )
    arr = np.array(rows, dtype=np.float64)
    # suppress duplicates (a trunk split into two clusters): keep the better supported one
    order = np.argsort(-arr[:, 3])
    kept: list[int] = []
    for i in order:
        if all(
            math.hypot(arr[i, 0] - arr[j, 0], arr[i, 1] - arr[j, 1])
            > 0.5 * max(arr[i, 2], arr[j, 2])
            for j in kept
        ):
            kept.append(int(i))
    arr = arr[np.sort(kept)]
    # absolute z of breast height at each stem: median z - h offset of nearby band points
    zbh = _breast_height_z(band, arr[:, :2], cfg.breast_height)
    heights = _stem_heights(band.canopy, arr[:, :2]) if band.canopy else np.full(len(arr), np.nan)
    return CloudStems.from_columns(
        xy=arr[:, :2],
        z=zbh,
        diameter=arr[:, 2],
        n_points=arr[:, 3].astype(np.int64),
        quality=np.clip(arr[:, 4], 0.0, 1.0),
        arc_deg=arr[:, 5],
        rms=arr[:, 6],
        n_slices=arr[:, 7].astype(np.int64),
        taper=arr[:, 8],
        height=heights,
        method="ours" if cfg.fit_method == "ours" else f"ours_{cfg.fit_method}",
        frame="cloud",
        spacing=sp2d,
    )


POOL_MAX_LEAN = math.tan(math.radians(10.0))
POOL_RESIDUAL_FACTOR = 1.5


def _pooled_stems(
    pts: FloatArray,
    hts: FloatArray,
    cid: NDArray[np.int64],
    sli: NDArray[np.int64],
    todo: NDArray[np.bool_],
    cfg: StemConfig,
    centers_h: FloatArray,
    noise_floor: float,
) -> list[tuple[float, ...]]:
    """One tilted-cylinder fit over the whole band for trunks with too few points per slice.

    A trunk partly hidden behind a nearer one, or in a sparse cloud, shows a few returns per
    slice: too few (< ``cfg.min_slice_points``) for a circle per slice, but together dozens
    of points on one cylinder. Candidates (``todo``) are the clusters the per-slice path
    could not judge: fewer than ``cfg.min_slices`` slices with ``cfg.min_slice_points``
    points (clusters with enough points per slice that failed the slice tests failed on
    shape and get no second chance). Those with >= 3 points in at least ``cfg.min_slices``
    slices spanning ``cfg.min_vertical_extent`` and >= 2 x ``cfg.min_slice_points`` points
    are fitted at once by a tilted circular cylinder (centre at breast height, lean,
    radius; taper ignored: over the 1.2 m band a taper of 1 cm/m moves the radius by < 6 mm
    at the band's ends and ~1 mm at its centre): damped Gauss-Newton batched over the
    candidates, Huber weights (scale 2 x the noise floor), trimming of |res| > 3 x 1.4826
    MAD, refit. One fit replaces the per-slice consistency checks, so the tests are
    stricter, all on the inliers:

    * RMS <= ``POOL_RESIDUAL_FACTOR`` (1.5) x the band's noise floor (a cylinder through
      many points must fit as well as the median slice circle), DBH in the window;
    * lean <= 10 degrees (a branch is >= 50 degrees from vertical); arc >=
      ``cfg.min_arc_deg``;
    * >= 2 x ``cfg.min_slice_points`` inliers, at least half of the cluster's points;
    * vertical consistency: >= ``cfg.min_slices`` + 1 slices holding >= 3 inliers, spanning
      ``cfg.min_vertical_extent``, and in every one of them the median residual within 3
      standard errors (1.25 x noise floor / sqrt(n)) or 5 % of r: stacked leaf blobs or a
      bush change radius from slice to slice.

    Returns rows like the band's ``(x, y, dbh, n_points, quality, arc, rms, n_slices, taper)``
    (taper NaN: not estimated). Pinned by ``test_pooled_fit_finds_sparse_trunks``.
    """
    ns = centers_h.shape[0]
    bh = cfg.breast_height
    kc = todo.shape[0]
    cnt_cs = np.bincount(cid * ns + sli, minlength=kc * ns).reshape(kc, ns)
    has = cnt_cs >= 3
    span = np.where(has, centers_h[None, :], -np.inf).max(axis=1) - np.where(
        has, centers_h[None, :], np.inf
    ).min(axis=1)
    ok_c = (
        todo
        & (has.sum(axis=1) >= cfg.min_slices)
        & (span >= cfg.min_vertical_extent - 1e-9)
        & (cnt_cs.sum(axis=1) >= 2 * cfg.min_slice_points)
    )
    if not ok_c.any():
        return []
    sel = ok_c[cid]
    p, hh, ids_old = pts[sel], hts[sel] - bh, cid[sel]
    cl, ids = np.unique(ids_old, return_inverse=True)
    ids = ids.astype(np.int64)
    k = cl.shape[0]
    s_i = sli[sel]
    first = fit_circles_batch(p, ids, "kasa")
    th = np.zeros((k, 5))
    th[:, 4] = np.nan
    th[first.segment_ids, :2] = first.centers
    th[first.segment_ids, 4] = first.radii
    alive = np.isfinite(th[:, 4]) & (th[:, 4] > 0)
    th[~alive, 4] = 0.1
    keep = alive[ids]
    f_scale = max(2.0 * noise_floor, 1e-3)

    def resid(t: FloatArray) -> tuple[FloatArray, FloatArray]:
        cx = t[ids, 0] + t[ids, 2] * hh
        cy = t[ids, 1] + t[ids, 3] * hh
        v = np.column_stack((p[:, 0] - cx, p[:, 1] - cy))
        dist = np.maximum(np.hypot(v[:, 0], v[:, 1]), 1e-9)
        return dist - t[ids, 4], v / dist[:, None]

    for rnd in range(2):
        for _ in range(10):
            d, n = resid(th)
            w = np.where(keep, np.minimum(1.0, f_scale / np.maximum(np.abs(d), 1e-12)), 0.0)
            J = np.column_stack(
                (-n[:, 0], -n[:, 1], -n[:, 0] * hh, -n[:, 1] * hh, -np.ones_like(d))
            )
            A = np.zeros((k, 5, 5))
            g = np.zeros((k, 5))
            for a in range(5):
                g[:, a] = np.bincount(ids, w * J[:, a] * d, minlength=k)
                for b in range(a, 5):
                    A[:, a, b] = A[:, b, a] = np.bincount(ids, w * J[:, a] * J[:, b], minlength=k)
            A += 1e-3 * np.einsum("kii->ki", A)[:, :, None] * np.eye(5)[None] + 1e-12 * np.eye(5)
            step = np.linalg.solve(A, -g[:, :, None])[:, :, 0]
            th = np.where(alive[:, None] & np.isfinite(step).all(axis=1)[:, None], th + step, th)
        if rnd == 0:
            d, _ = resid(th)
            ad = np.abs(d)
            mad = np.full(k, np.inf)
            order = np.lexsort((ad, ids))
            s_ids = ids[order]
            starts = np.flatnonzero(np.r_[True, s_ids[1:] != s_ids[:-1]])
            cnts = np.diff(np.r_[starts, s_ids.size])
            mad[s_ids[starts]] = ad[order][starts + cnts // 2]
            keep = alive[ids] & (ad <= np.maximum(3.0 * 1.4826 * mad, 0.001)[ids])
    d, n = resid(th)
    r = th[:, 4]
    nin = np.bincount(ids[keep], minlength=k)
    rms = np.sqrt(np.bincount(ids[keep], d[keep] ** 2, minlength=k) / np.maximum(nin, 1))
    cxy = th[:, :2]
    # arc: the directions of the points seen from the axis at their heights
    arcs = _segment_arcs(n[keep], ids[keep], k, np.zeros((k, 2)))
    seg = ids * ns + s_i
    n_sl = np.bincount(seg[keep], minlength=k * ns).reshape(k, ns)
    has_in = n_sl >= 3
    rows: list[tuple[float, ...]] = []
    for j in np.flatnonzero(alive):
        rj = float(r[j])
        tol_r = POOL_RESIDUAL_FACTOR * noise_floor
        if not (cfg.min_diameter / 2 <= rj <= cfg.max_diameter / 2 and rms[j] <= tol_r):
            continue
        if math.hypot(th[j, 2], th[j, 3]) > POOL_MAX_LEAN or arcs[j] < cfg.min_arc_deg:
            continue
        n_all = int(cnt_cs[cl[j]].sum())
        if nin[j] < 2 * cfg.min_slice_points or nin[j] < 0.5 * n_all:
            continue
        hs = has_in[j]
        if not hs[-1]:
            continue  # a stem goes on above the band; a shrub or a stack of leaf blobs ends
        if hs.sum() < cfg.min_slices + 1 or np.ptp(centers_h[hs]) < cfg.min_vertical_extent - 1e-9:
            continue
        mine = keep & (ids == j)
        # each slice's median residual must vanish within its standard error (1.25 sigma /
        # sqrt(n) for a median) x 3, or 5 % of r (taper over the band)
        bad = False
        for s in np.flatnonzero(hs):
            rs = d[mine & (s_i == s)]
            tol_s = max(3.0 * 1.25 * noise_floor / math.sqrt(rs.size), 0.05 * rj)
            bad |= abs(float(np.median(rs))) > tol_s
        if bad:
            continue
        frac = float(hs.sum()) / max(int((cnt_cs[cl[j]] > 0).sum()), 1)
        q = frac * min(1.0, arcs[j] / 120.0) * min(1.0, noise_floor / max(rms[j], 1e-6))
        rows.append(
            (
                float(cxy[j, 0]),
                float(cxy[j, 1]),
                2 * rj,
                int(nin[j]),
                q,
                float(arcs[j]),
                float(rms[j]),
                int(hs.sum()),
                math.nan,
            )
        )
    return rows


def _breast_height_z(band: _Band, xy: FloatArray, bh: float) -> FloatArray:
    from scipy.spatial import cKDTree

    if band.xy.shape[0] == 0 or xy.shape[0] == 0:
        return np.full(xy.shape[0], np.nan)
    off = band.z - band.h  # ground z under each band point
    tree = cKDTree(band.xy)
    _, idx = tree.query(xy, k=min(16, band.xy.shape[0]))
    idx = np.atleast_2d(idx)
    return np.asarray(np.median(off[idx], axis=1) + bh, dtype=np.float64)


# --------------------------------------------------------------------------------------------
# streaming over files
# --------------------------------------------------------------------------------------------


def detect_stems_file(
    path: str | Path,
    config: StemConfig | MunjerConfig | None = None,
    *,
    chunk_size: int = 2_000_000,
    on_chunk: Callable[[int, int], None] | None = None,
    sensor: SensorPositions | None = None,
    topic: str | None = None,
) -> CloudStems:
    """Run a detector on a cloud file, streaming LAS/LAZ in chunks.

    ``StemConfig`` (ours) on LAS/LAZ: pass 1 builds the ground raster (and z range), pass 2
    keeps only the slice band (and a canopy-height raster if heights are requested); memory is
    bounded by the chunk size plus the band. Other formats (PLY, PCD, text, bags: ``topic``)
    are read whole and go to :func:`detect_stems`. ``MunjerConfig``: the cloud is read whole
    (a lidar frame is small).

    ``sensor`` gives each point's sensor position (a station, or a trajectory interpolated at
    the points' time stamps, :class:`stemmap.cloud.sensor.SensorPositions`) for the along-ray
    refinement of the slice fits (``detect_stems(..., origins=)``). Only ``ours`` uses it:
    with ``munjer2025`` or the Kasa fit it is a ConfigError rather than silently ignored.

    ``on_chunk(points_done, points_total)`` is called after each chunk of each pass (for a
    progress bar; ``points_total`` counts both passes).
    """
    from stemmap.io.clouds import count_points, iter_cloud_chunks, point_fields, read_cloud

    cfg = config or StemConfig()
    src = repr(str(path))
    if sensor is not None and (isinstance(cfg, MunjerConfig) or cfg.fit_method == "kasa"):
        name = "munjer2025" if isinstance(cfg, MunjerConfig) else "the Kasa fit (ours_kasa)"
        raise ConfigError(
            f"sensor positions are used only by preset 'ours'; {name} has no along-ray "
            "refinement. Drop the sensor positions or use preset 'ours'."
        )
    if isinstance(cfg, MunjerConfig) or Path(path).suffix.lower() not in (".las", ".laz"):
        cloud = read_cloud(path, topic=topic)
        if on_chunk:
            on_chunk(len(cloud), len(cloud))
        if isinstance(cfg, MunjerConfig):
            return detect_stems_munjer(cloud.xyz, cfg)
        origins = None
        if sensor is not None:
            times = None
            if sensor.needs_time:
                times = cloud.fields[sensor.pick_time_field(cloud.fields, src)]
            origins = sensor.origins(len(cloud), times, src)
        return detect_stems(cloud.xyz, cfg, origins=origins)
    tfield: str | None = None
    if sensor is not None and sensor.needs_time:
        tfield = sensor.pick_time_field(point_fields(path) or (), src)
    total = count_points(path)
    done = 0
    acc = GroundAccumulator(cfg.ground_cell)
    zmin, zmax = math.inf, -math.inf
    n_total = 0
    for chunk in iter_cloud_chunks(path, chunk_size):
        xyz = chunk.xyz
        if xyz.shape[0] == 0:
            continue
        n_total += xyz.shape[0]
        zmin = min(zmin, float(xyz[:, 2].min()))
        zmax = max(zmax, float(xyz[:, 2].max()))
        acc.update(xyz)
        done += xyz.shape[0]
        if on_chunk:
            on_chunk(done, 2 * (total or n_total))
    if n_total == 0:
        raise InputError(f"{src} holds no points.")
    is_slice = cfg.slice_mode == "always" or (cfg.slice_mode == "auto" and zmax - zmin < 1.0)
    cfg = _slice_setup(cfg, zmin, zmax, is_slice)
    ground = None if is_slice else acc.model()
    lo, hi = cfg.band
    xs, hs, zs, os_ = [], [], [], []
    canopy: dict[str, Any] = {}
    for chunk in iter_cloud_chunks(path, chunk_size, fields=(tfield,) if tfield else ()):
        xyz = chunk.xyz
        if ground is None:
            h = xyz[:, 2]
        else:
            h = ground.height_of(xyz)
            if cfg.estimate_height:
                canopy = _canopy_update(canopy, xyz[:, :2], h)
        m = (h >= lo) & (h <= hi)
        xs.append(xyz[m, :2])
        hs.append(h[m])
        zs.append(xyz[m, 2])
        if sensor is not None:  # only the band's points need a sensor position
            times = None if tfield is None else chunk.fields[tfield][m]
            os_.append(sensor.origins(int(m.sum()), times, src))
        done += xyz.shape[0]
        if on_chunk:
            on_chunk(done, 2 * n_total)
    band = _Band(
        np.concatenate(xs),
        np.concatenate(hs),
        np.concatenate(zs),
        canopy,
        origins=np.concatenate(os_) if sensor is not None else None,
    )
    log.info("%s: %d points, %d in the slice band", path, n_total, band.xy.shape[0])
    return _stems_from_band(band, cfg, slice_cloud=is_slice)
