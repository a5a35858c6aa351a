"""EB-LiDAR stem detection (Munjer et al. 2025, §3.2-3.3, Table 1) and proximity association
across frames."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.cloud.cluster import dbscan
from stemmap.cloud.filters import as_xyz, pass_through, voxel_downsample
from stemmap.cloud.result import CloudStems
from stemmap.cloud.shape import cluster_covariances, major_axis_tilt_deg, pca_eccentricity
from stemmap.errors import ConfigError, InputError
from stemmap.scan.circle import fit_circles_batch
from stemmap.types import FloatArray

__all__ = [
    "CLUSTER_STAGES",
    "MunjerClusters",
    "MunjerConfig",
    "associate_proximity",
    "detect_stems_munjer",
    "level_to_ground",
    "munjer_clusters",
]


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
    eccentricity_axes : "major_minor" or "largest" -- which two eigenvalues of the cluster's 3D
        covariance make ``e``. The paper says "two principal eigenvalues, lambda1 > lambda2";
        "largest" (the two biggest) puts a 16-beam trunk cluster at e ~ 1.4-3.5 (its height
        band against its width), never in [10, 20]; "major_minor" (biggest over smallest: a
        partial trunk is a curved sheet, thin in depth) gives trunks e ~ 6-16. Default
        "major_minor"; the evidence is in docs/algorithms/cloud.md.
    ground_relative : bool -- apply ``box_z`` to the height relative to the ground plane under
        the sensor (:func:`level_to_ground`) instead of the raw sensor z. The paper's z in
        (-0.5, 0) assumes flat ground: on an 8 % slope the ground 6 m ahead is 0.5 m higher and
        enters the box, its rings swallow the trunk bases in DBSCAN. On flat ground both agree.
        Default False (the published box): it helps on sloped simulated stands (5 -> 8 of 10
        trees) but a real-cloud check was inconclusive (docs/algorithms/cloud.md).
    window : int, >= 1 -- lidar frames clustered together by
        :func:`stemmap.slam.munjer.eb_lidar_observations`: each frame's pass-through points
        joined with those of the ``window - 1`` frames before it, moved into its lidar frame
        with the motion source's poses, its detections (minPts from one frame) added to the
        frame's own. The paper is silent (it clusters "the filtered point cloud P'" of a
        moving robot); 1 = strictly per frame, the Munjer pipeline's default (as published):
        5 frames gain trees on the simulator and on virtual frames of a real plot, with no
        false tree on either (docs/algorithms/cloud.md, "Accumulated frames").
        :func:`detect_stems_munjer` itself takes one cloud (with ``frame_ids`` for a joined
        one).
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
    eccentricity_axes: str = "major_minor"
    max_tilt_deg: float | None = 45.0
    ground_relative: bool = False
    window: int = 1

    def __post_init__(self) -> None:
        if not (self.voxel > 0 and self.eps > 0 and self.min_points >= 1):
            raise ConfigError("munjer2025 needs voxel > 0, eps > 0 and min_points >= 1.")
        if self.window < 1:
            raise ConfigError(f"window must be >= 1 frame, got {self.window}.")
        lo, hi = self.eccentricity_range
        if not hi >= lo >= 1:
            raise ConfigError(f"eccentricity_range must satisfy 1 <= lo <= hi, got {lo}, {hi}.")
        if self.max_tilt_deg is not None and not 0 < self.max_tilt_deg <= 90:
            raise ConfigError(
                f"max_tilt_deg must lie in (0, 90] or be None, got {self.max_tilt_deg}."
            )
        if self.eccentricity_axes not in ("largest", "major_minor"):
            raise ConfigError(
                "eccentricity_axes must be 'major_minor' or 'largest', got "
                f"{self.eccentricity_axes!r}."
            )


@dataclass(frozen=True, eq=False)
class MunjerClusters:
    """Every DBSCAN cluster of one EB-LiDAR input and the stage that kept or rejected it
    (:func:`munjer_clusters`; the detector and the cause table share it).

    Attributes
    ----------
    points : (M, 3) metres -- the voxel-averaged pass-through points (lidar frame), eq. (2)
    labels : (M,) int -- DBSCAN cluster of each point, -1 for noise (§3.3)
    point_frames : (M,) int or None -- capture of each point (joined frames only)
    centroid : (K, 3) metres; n_points : (K,) int -- cluster centroids and sizes
    eccentricity : (K,) -- eq. (4) over ``config.eccentricity_axes``
    tilt_deg : (K,) -- principal axis from vertical (0-90 degrees)
    dense : (K,) bool -- ``min_points`` points (from one capture when frames are joined)
    in_window : (K,) bool -- ``lo <= eccentricity <= hi``
    vertical : (K,) bool -- ``tilt_deg <= max_tilt_deg`` (all True when the check is off)
    center : (K, 2) metres, radius : (K,) metres, rms : (K,) metres -- circle fit of the xy
        projection, NaN for clusters that did not reach it (only dense, in-window, vertical
        clusters are fitted: the pipeline's order)
    fit_ok : (K,) bool -- fitted, and the residual std <= ``fit_std_max`` (Table 1)
    eccentricity_range : the window ``in_window`` was tested against
    reason : str -- why there is no cluster at all ("" otherwise)
    """

    points: FloatArray
    labels: NDArray[np.int64]
    point_frames: NDArray[np.int64] | None
    centroid: FloatArray
    n_points: NDArray[np.int64]
    eccentricity: FloatArray
    tilt_deg: FloatArray
    dense: NDArray[np.bool_]
    in_window: NDArray[np.bool_]
    vertical: NDArray[np.bool_]
    center: FloatArray
    radius: FloatArray
    rms: FloatArray
    fit_ok: NDArray[np.bool_]
    eccentricity_range: tuple[float, float] = (10.0, 20.0)
    reason: str = ""

    def __len__(self) -> int:
        return int(self.n_points.shape[0])

    @property
    def accepted(self) -> NDArray[np.bool_]:
        """(K,) bool: clusters EB-LiDAR reports as stems (every stage passed)."""
        return self.dense & self.in_window & self.vertical & self.fit_ok

    def stage(self) -> NDArray[np.str_]:
        """(K,) the first stage each cluster failed, in the pipeline's order -- one of
        :data:`CLUSTER_STAGES` (``"accepted"`` when none failed)."""
        out = np.full(len(self), "accepted", dtype="<U17")
        out[~self.fit_ok] = "circle_fit"
        out[~self.vertical] = "tilt"
        low = self.eccentricity < self.eccentricity_range[0]
        out[~self.in_window] = np.where(low, "eccentricity_low", "eccentricity_high")[
            ~self.in_window
        ]
        out[~self.dense] = "min_points"
        return out

    def stems(self) -> CloudStems:
        """The accepted clusters as :class:`CloudStems` (what :func:`detect_stems_munjer`
        returns)."""
        if len(self) == 0:
            return CloudStems.empty("munjer2025", reason=self.reason)
        ids = np.flatnonzero(self.accepted)
        if ids.size == 0 and not (self.dense & self.in_window & self.vertical).any():
            return CloudStems.empty("munjer2025", reason=self.reason)
        return CloudStems.from_columns(
            xy=self.center[ids],
            z=self.centroid[ids, 2],
            diameter=2 * self.radius[ids],
            n_points=self.n_points[ids],
            rms=self.rms[ids],
            eccentricity=self.eccentricity[ids],
            method="munjer2025",
            frame="lidar",
        )


#: Stages of :meth:`MunjerClusters.stage`, in the pipeline's order.
CLUSTER_STAGES = (
    "min_points",
    "eccentricity_low",
    "eccentricity_high",
    "tilt",
    "circle_fit",
    "accepted",
)


def _no_clusters(points: FloatArray, reason: str) -> MunjerClusters:
    z, zb, zi = np.zeros(0), np.zeros(0, dtype=bool), np.zeros(0, dtype=np.int64)
    return MunjerClusters(
        points=points,
        labels=np.full(points.shape[0], -1, dtype=np.int64),
        point_frames=None,
        centroid=np.zeros((0, 3)),
        n_points=zi,
        eccentricity=z,
        tilt_deg=z,
        dense=zb,
        in_window=zb,
        vertical=zb,
        center=np.zeros((0, 2)),
        radius=z,
        rms=z,
        fit_ok=zb,
        reason=reason,
    )


def munjer_clusters(
    xyz: ArrayLike, config: MunjerConfig | None = None, *, frame_ids: ArrayLike | None = None
) -> MunjerClusters:
    """EB-LiDAR's stages on one lidar frame, every cluster kept with its outcome (Munjer et
    al. 2025, §3.2-3.3): pass-through box -> voxel grid, eq. (2) -> DBSCAN(eps, minPts) ->
    covariance, eq. (3), and eccentricity, eq. (4) -> tilt -> circle fit of the projection.
    :func:`detect_stems_munjer` is ``munjer_clusters(...).stems()``; parameters as there.
    """
    cfg = config or MunjerConfig()
    p = as_xyz(xyz)
    zb = level_to_ground(p) if cfg.ground_relative else p
    inside = pass_through(zb, x=cfg.box_x, y=cfg.box_y, z=cfg.box_z)
    p = p[inside]
    if p.shape[0] < cfg.min_points:
        return _no_clusters(
            np.zeros((0, 3)), f"fewer than {cfg.min_points} points inside the pass-through box"
        )
    vid = None
    if frame_ids is None:
        v: FloatArray = np.asarray(voxel_downsample(p, cfg.voxel), dtype=np.float64)
    else:
        fid = np.asarray(frame_ids).reshape(-1)
        if fid.shape[0] != inside.shape[0]:
            raise InputError(f"{fid.shape[0]} frame ids for {inside.shape[0]} points.")
        _, fid = np.unique(fid[inside], return_inverse=True)
        fid = fid.reshape(-1)
        per = [np.asarray(voxel_downsample(p[fid == k], cfg.voxel)) for k in range(fid.max() + 1)]
        v = np.vstack(per).astype(np.float64)
        vid = np.repeat(np.arange(len(per)), [len(q) for q in per])
    lab = dbscan(v, cfg.eps, cfg.min_points).astype(np.int64)
    if lab.size == 0 or lab.max() < 0:
        return _no_clusters(v, "DBSCAN found no cluster")
    cen, cov, sizes = cluster_covariances(v, lab)
    ecc = pca_eccentricity(cov, cfg.eccentricity_axes)
    tilt = major_axis_tilt_deg(cov)
    lo, hi = cfg.eccentricity_range
    dense = sizes >= cfg.min_points
    if vid is not None:
        ok = lab >= 0
        n_f = int(vid.max()) + 1
        per_frame = np.bincount(lab[ok] * n_f + vid[ok], minlength=sizes.size * n_f)
        dense &= per_frame.reshape(sizes.size, n_f).max(axis=1) >= cfg.min_points
    in_window = (ecc >= lo) & (ecc <= hi)
    vertical = (
        np.ones(sizes.size, dtype=bool) if cfg.max_tilt_deg is None else tilt <= cfg.max_tilt_deg
    )
    k = sizes.size
    center, radius, rms = np.full((k, 2), np.nan), np.full(k, np.nan), np.full(k, np.nan)
    fit_ok = np.zeros(k, dtype=bool)
    cand = np.flatnonzero(dense & in_window & vertical)
    reason = ""
    if cand.size == 0:
        t = "" if cfg.max_tilt_deg is None else f" and a tilt <= {cfg.max_tilt_deg} deg"
        reason = f"no cluster has an eccentricity in [{lo}, {hi}]{t}"
    else:
        sel = np.isin(lab, cand)
        fits = fit_circles_batch(v[sel, :2], lab[sel], cfg.fit_method, edges=None)
        ids = fits.segment_ids
        center[ids], radius[ids], rms[ids] = fits.centers, fits.radii, fits.rms
        fit_ok[ids] = fits.ok & (fits.rms <= cfg.fit_std_max)
    return MunjerClusters(
        points=v,
        labels=lab,
        point_frames=vid,
        centroid=cen,
        n_points=sizes,
        eccentricity=ecc,
        tilt_deg=tilt,
        dense=dense,
        in_window=in_window,
        vertical=vertical,
        center=center,
        radius=radius,
        rms=rms,
        fit_ok=fit_ok,
        eccentricity_range=(float(lo), float(hi)),
        reason=reason,
    )


def detect_stems_munjer(
    xyz: ArrayLike, config: MunjerConfig | None = None, *, frame_ids: ArrayLike | None = None
) -> CloudStems:
    """EB-LiDAR stem detection in one lidar frame (Munjer et al. 2025, §3.2-3.3).

    Parameters
    ----------
    xyz : array_like (N, 3), metres, lidar frame (x forward, z up, origin at the sensor)
    config : MunjerConfig, default the published Table 1 values
    frame_ids : array_like (N,) int, optional -- when ``xyz`` joins several captures
        (:func:`stemmap.slam.munjer.accumulate_frames`), the capture of each point. Then the
        voxel grid, eq. (2), averages within a capture only, and a cluster is kept only if
        ``config.min_points`` of its points come from one capture: minPts stays a per-capture
        density, as the paper applies it; joining captures may sharpen a cluster's shape but
        may not make sparse returns (ground, understory) dense enough (ours; without it joined
        frames add false trees on a real plot, docs/algorithms/cloud.md, "Accumulated frames").

    Returns
    -------
    CloudStems
        One row per accepted cluster: centre and diameter from the circle fit of its xy
        projection, ``z`` its mean height, ``eccentricity`` its lambda1/lambda2.

    Notes
    -----
    Pipeline: pass-through box (§3.2) -> voxel-grid averaging, eq. (2) -> DBSCAN(eps, minPts)
    (§3.3) -> covariance of each cluster, eq. (3), and eccentricity ``e = lambda1 / lambda2``,
    eq. (4), over the eigenvalues ``config.eccentricity_axes`` names (default the largest over
    the smallest of the 3D covariance) -> keep ``10 <= e <= 20``
    (§3.3: "between 10 and 20"; Table 1 names 20 the cutoff) whose principal axis is within
    ``config.max_tilt_deg`` of vertical (the abstract's "vertically elongated") -> circle fit
    of the cluster's 2D projection, rejected when the residual standard deviation exceeds
    0.1 m (Table 1). The stages run in :func:`munjer_clusters`, which keeps every cluster's
    outcome (the cause table, ``benchmarks/munjer2025_causes.py``, reads it).
    """
    return munjer_clusters(xyz, config, frame_ids=frame_ids).stems()


def level_to_ground(xyz: ArrayLike, cell: float = 1.0, max_residual: float = 0.15) -> FloatArray:
    """Points with z replaced by ``z - (g(x, y) - g(0, 0))``, ``g`` the ground plane of the frame.

    Ours (Munjer et al. 2025 apply the pass-through box in the raw lidar frame). The plane
    ``g = a + b x + c y`` is fitted by least squares to the lowest point of every ``cell`` m
    cell below the sensor (z < 0; of equal minima the one of smallest x, then y, so the plane
    does not depend on the point order), three rounds dropping cells more than
    ``max_residual`` above it (trunk or bush bottoms); with fewer than 3 cells the points are
    returned unchanged.
    """
    p = as_xyz(xyz)
    below = p[p[:, 2] < 0]
    if below.shape[0] < 3:
        return p
    ij = np.floor(below[:, :2] / cell).astype(np.int64)
    _, inv = np.unique(ij, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    zmin = np.full(int(inv.max()) + 1, np.inf)
    np.minimum.at(zmin, inv, below[:, 2])
    low = np.flatnonzero(below[:, 2] == zmin[inv])
    # of equal cell minima the one of smallest x, then y: the plane does not depend on the
    # point order (as the default preset's ground, docs/algorithms/cloud.md "Point order")
    low = low[np.lexsort((below[low, 1], below[low, 0], inv[low]))]
    _, keep_first = np.unique(inv[low], return_index=True)
    g = below[low[keep_first]]
    ok = np.ones(g.shape[0], bool)
    coef = None
    for _ in range(3):
        if ok.sum() < 3:
            break
        A = np.column_stack((np.ones(int(ok.sum())), g[ok, 0], g[ok, 1]))
        coef = np.linalg.lstsq(A, g[ok, 2], rcond=None)[0]
        res = g[:, 2] - (coef[0] + coef[1] * g[:, 0] + coef[2] * g[:, 1])
        ok = res < max_residual
    if coef is None:
        return p
    out = p.copy()
    out[:, 2] -= coef[1] * p[:, 0] + coef[2] * p[:, 1]
    return out


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
