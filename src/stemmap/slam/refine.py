"""Kalman refinement of tree positions in the map frame (Munjer et al. 2025, §3.6).

Munjer et al. transform every tree detection into the global frame (their eq. 13) and then apply
"a Kalman Filter ... to further refine these positions by mitigating measurement noise and sensor
drift". The paper gives no matrices; we write the filter down (decision recorded in
docs/algorithms/slam-frontends.md):

* state: the tree position ``t = (x, y)`` in the map frame, one independent filter per tree;
* process model: static tree, ``t_k = t_{k-1} + w``, ``w ~ N(0, q * I)`` per update (``q = 0``
  by default; ``q > 0`` lets the estimate follow slow drift of the map frame, as the paper says);
* measurement: the detection transformed to the map frame, ``z = t + v`` with covariance
  ``R = J_p Σ_pose J_pᵀ + J_z Σ_polar J_zᵀ`` -- the *pose uncertainty is propagated into the
  observation covariance* (first order), see :func:`world_observation_covariance`.

With ``q = 0`` the filter equals the information-weighted mean of the detections; it is run
sequentially (vectorised across trees: the k-th update of every tree happens in one numpy step)
so ``q > 0`` works too.

References
----------
.. [Munjer2025] Munjer et al., "LiDAR vs depth-image tree mapping", §3.6, eqs. (12)-(15).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.errors import ConfigError, InputError
from stemmap.types import FloatArray, StemMap

__all__ = [
    "RefinedTrees",
    "kalman_refine_trees",
    "refine_stem_map",
    "world_observation_covariance",
    "world_observation_jacobians",
]


def world_observation_jacobians(
    poses: ArrayLike,
    ranges: ArrayLike,
    bearings: ArrayLike,
    sensor_offset: tuple[float, float] = (0.0, 0.0),
) -> tuple[FloatArray, FloatArray]:
    """``J_p`` (K, 2, 3) and ``J_z`` (K, 2, 2) of :func:`world_observation_covariance`: the
    map-frame detection's derivatives by the vehicle pose and by (range, bearing)."""
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    r = np.asarray(ranges, dtype=np.float64).reshape(-1)
    b = np.asarray(bearings, dtype=np.float64).reshape(-1)
    if not (p.shape[0] == r.shape[0] == b.shape[0]):
        raise InputError(
            f"world_observation_covariance: {p.shape[0]} poses, {r.shape[0]} ranges and "
            f"{b.shape[0]} bearings must agree."
        )
    a, bb = sensor_offset
    c, s = np.cos(p[:, 2]), np.sin(p[:, 2])
    sx = p[:, 0] + a * c - bb * s
    sy = p[:, 1] + a * s + bb * c
    ang = p[:, 2] + b
    ca, sa = np.cos(ang), np.sin(ang)
    tx = sx + r * ca
    ty = sy + r * sa
    k = p.shape[0]
    Jp = np.zeros((k, 2, 3))
    Jp[:, 0, 0] = 1.0
    Jp[:, 1, 1] = 1.0
    Jp[:, 0, 2] = -(ty - p[:, 1])
    Jp[:, 1, 2] = tx - p[:, 0]
    Jz = np.empty((k, 2, 2))
    Jz[:, 0, 0] = ca
    Jz[:, 0, 1] = -r * sa
    Jz[:, 1, 0] = sa
    Jz[:, 1, 1] = r * ca
    return Jp, Jz


def world_observation_covariance(
    poses: ArrayLike,
    pose_covs: ArrayLike,
    ranges: ArrayLike,
    bearings: ArrayLike,
    *,
    sigma_range: float | ArrayLike,
    sigma_bearing: float | ArrayLike,
    sensor_offset: tuple[float, float] = (0.0, 0.0),
) -> FloatArray:
    """Covariance (K, 2, 2) of range-bearing detections mapped to the world frame.

    With the sensor at ``s = p + R(θ)(a, b)`` and the tree at
    ``t = s + r (cos(θ+φ), sin(θ+φ))``::

        J_p = [[1, 0, -(t_y - p_y)], [0, 1, t_x - p_x]]            (d t / d(x, y, θ))
        J_z = [[cos(θ+φ), -r sin(θ+φ)], [sin(θ+φ), r cos(θ+φ)]]   (d t / d(r, φ))
        R   = J_p Σ_pose J_pᵀ + J_z diag(σ_r², σ_φ²) J_zᵀ

    Parameters
    ----------
    poses : ndarray (K, 3)
        Vehicle pose of each detection.
    pose_covs : ndarray (K, 3, 3) or (3, 3)
        Pose covariance (NaN entries are treated as zero, i.e. a known pose).
    ranges, bearings : ndarray (K,)
    sigma_range : float or ndarray (K,), m, >= 0
    sigma_bearing : float or ndarray (K,), rad, >= 0
        One sigma for every detection, or each detection's own (e.g. the FastSLAM floor plus
        a detector's noise model, :func:`refine_stem_map` ``noise``).
    sensor_offset : (a, b), m
    """
    sr = np.asarray(sigma_range, dtype=np.float64)
    sb = np.asarray(sigma_bearing, dtype=np.float64)
    if np.any(sr < 0) or np.any(sb < 0):
        raise ConfigError("sigma_range and sigma_bearing must be >= 0.")
    Jp, Jz = world_observation_jacobians(poses, ranges, bearings, sensor_offset)
    S = np.nan_to_num(np.broadcast_to(np.asarray(pose_covs, dtype=np.float64), (Jp.shape[0], 3, 3)))
    if sr.ndim == 0 and sb.ndim == 0:
        Rz = np.diag([float(sr) ** 2, float(sb) ** 2])
    else:
        Rz = np.zeros((Jz.shape[0], 2, 2))
        Rz[:, 0, 0] = np.broadcast_to(sr, Jz.shape[:1]) ** 2
        Rz[:, 1, 1] = np.broadcast_to(sb, Jz.shape[:1]) ** 2
    out: FloatArray = Jp @ S @ np.swapaxes(Jp, 1, 2) + Jz @ Rz @ np.swapaxes(Jz, 1, 2)
    return 0.5 * (out + np.swapaxes(out, 1, 2))


class RefinedTrees:
    """Result of :func:`kalman_refine_trees`: ``xy`` (N, 2), ``cov`` (N, 2, 2), ``n_obs`` (N,)."""

    __slots__ = ("cov", "n_obs", "xy")

    def __init__(self, xy: FloatArray, cov: FloatArray, n_obs: NDArray[np.int64]) -> None:
        self.xy = xy
        self.cov = cov
        self.n_obs = n_obs

    def __len__(self) -> int:
        return int(self.xy.shape[0])


def kalman_refine_trees(
    z: ArrayLike,
    R: ArrayLike,
    tree_index: ArrayLike,
    n_trees: int | None = None,
    *,
    process_noise: float = 0.0,
) -> RefinedTrees:
    """Per-tree Kalman filter over map-frame detections, Munjer et al. 2025 §3.6.

    For each tree, detections are processed in the given order (time order)::

        P⁻ = P + q I;   K = P⁻ (P⁻ + R_k)⁻¹;   t = t + K (z_k - t);   P = (I - K) P⁻

    initialised with the first detection (``t = z_1``, ``P = R_1``).

    Parameters
    ----------
    z : ndarray (K, 2), m
        Detections in the map frame.
    R : ndarray (K, 2, 2)
        Their covariances (e.g. from :func:`world_observation_covariance`).
    tree_index : ndarray (K,), int
        Tree each detection belongs to (from data association); negative = unassociated, skipped.
    n_trees : int, optional
        Number of trees (default ``max(tree_index) + 1``); trees without detections get NaN.
    process_noise : float, m², >= 0
        ``q`` added to the covariance before each update.

    Returns
    -------
    RefinedTrees

    Raises
    ------
    InputError
        On inconsistent shapes or non-finite detections.

    Examples
    --------
    >>> import numpy as np
    >>> out = kalman_refine_trees([[0.0, 0.0], [1.0, 0.0]], [np.eye(2), np.eye(2)], [0, 0])
    >>> out.xy.tolist(), float(out.cov[0, 0, 0])
    ([[0.5, 0.0]], 0.5)
    """
    zz = np.asarray(z, dtype=np.float64).reshape(-1, 2)
    RR = np.asarray(R, dtype=np.float64).reshape(-1, 2, 2)
    idx = np.asarray(tree_index, dtype=np.int64).reshape(-1)
    if not (zz.shape[0] == RR.shape[0] == idx.shape[0]):
        raise InputError(
            f"kalman_refine_trees: {zz.shape[0]} detections, {RR.shape[0]} covariances and "
            f"{idx.shape[0]} tree indices must agree."
        )
    if not np.all(np.isfinite(zz)) or not np.all(np.isfinite(RR)):
        raise InputError("kalman_refine_trees: detections and covariances must be finite.")
    if process_noise < 0:
        raise ConfigError(f"process_noise must be >= 0 m^2, got {process_noise}.")
    n = int(n_trees) if n_trees is not None else (int(idx.max()) + 1 if idx.size else 0)
    ok = idx >= 0
    if np.any(idx[ok] >= n):
        raise InputError(f"kalman_refine_trees: tree_index {idx.max()} >= n_trees {n}.")
    xy = np.full((n, 2), np.nan)
    P = np.full((n, 2, 2), np.nan)
    n_obs = np.bincount(idx[ok], minlength=n).astype(np.int64)
    sel = np.flatnonzero(ok)
    if sel.size == 0:
        return RefinedTrees(xy, P, n_obs)
    # rank of each detection within its tree (stable, keeps time order)
    order = sel[np.argsort(idx[sel], kind="stable")]
    t_sorted = idx[order]
    starts = np.searchsorted(t_sorted, t_sorted, side="left")
    rank = np.arange(order.size) - starts
    first = order[rank == 0]
    xy[idx[first]] = zz[first]
    P[idx[first]] = RR[first]
    eye = np.eye(2)
    for k in range(1, int(rank.max()) + 1):
        d = order[rank == k]
        j = idx[d]
        Pm = P[j] + process_noise * eye
        S = Pm + RR[d]
        K = Pm @ np.linalg.inv(S)
        xy[j] = xy[j] + np.einsum("nij,nj->ni", K, zz[d] - xy[j])
        Pn = (eye - K) @ Pm
        P[j] = 0.5 * (Pn + np.swapaxes(Pn, 1, 2))
    return RefinedTrees(xy, P, n_obs)


def refine_stem_map(
    stem_map: StemMap,
    poses: ArrayLike,
    frame_ptr: ArrayLike,
    ranges: ArrayLike,
    bearings: ArrayLike,
    *,
    sigma_range: float,
    sigma_bearing: float,
    sensor_offset: tuple[float, float] = (0.0, 0.0),
    pose_covs: ArrayLike | None = None,
    gate: float = 1.0,
    process_noise: float = 0.0,
    noise: ArrayLike | None = None,
) -> StemMap:
    """Refine a stem map with every detection, Munjer 2025 §3.6 (post-step for any back-end).

    Each detection is mapped to the world at its frame's pose, associated with the nearest
    mapped tree within ``gate`` (a tree takes at most one detection per frame, the closest),
    and every tree is re-estimated by :func:`kalman_refine_trees` with the detection covariance
    of :func:`world_observation_covariance` (pose covariance propagated).

    Parameters
    ----------
    stem_map : StemMap
    poses : ndarray (F, 3)
        Vehicle pose at every frame.
    frame_ptr : ndarray (F + 1,), int
        Detections of frame f are ``[ptr[f], ptr[f+1])``.
    ranges, bearings : ndarray (K,)
        Detections in the sensor frame.
    sigma_range, sigma_bearing : float
    sensor_offset : (a, b), m
    pose_covs : ndarray (F, 3, 3), optional
        Pose covariance per frame (default: poses treated as exact).
    gate : float, m
    process_noise : float, m²
    noise : ndarray (K, 2), optional
        Each detection's own (sigma_range, sigma_bearing) (``TreeFrames.noise``), added in
        quadrature to ``sigma_range`` / ``sigma_bearing`` (NaN: nothing added); ours, as
        :class:`~stemmap.slam.fastslam.FastSlam` ``detection_noise``.

    Returns
    -------
    StemMap
        Same trees (ids, diameters) with refined positions, covariances and detection counts;
        trees that received no detection are unchanged.
    """
    from dataclasses import replace

    from stemmap.slam.base import observation_to_world

    p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    ptr = np.asarray(frame_ptr, dtype=np.int64).reshape(-1)
    r = np.asarray(ranges, dtype=np.float64).reshape(-1)
    b = np.asarray(bearings, dtype=np.float64).reshape(-1)
    if ptr.shape[0] != p.shape[0] + 1 or ptr[-1] != r.shape[0] or b.shape != r.shape:
        raise InputError(
            f"refine_stem_map: {p.shape[0]} poses need {p.shape[0] + 1} frame pointers ending at "
            f"the {r.shape[0]} detections; got {ptr.shape[0]} pointers and {b.shape[0]} bearings."
        )
    if len(stem_map) == 0 or r.size == 0:
        return stem_map
    if not gate > 0:
        raise ConfigError(f"refine_stem_map: gate must be > 0 m, got {gate}.")
    frame = np.repeat(np.arange(p.shape[0]), np.diff(ptr))
    z = observation_to_world(p[frame], r, b, sensor_offset)
    S = np.zeros((p.shape[0], 3, 3)) if pose_covs is None else np.asarray(pose_covs, np.float64)
    s_r: float | FloatArray = sigma_range
    s_b: float | FloatArray = sigma_bearing
    if noise is not None:
        nz = np.nan_to_num(np.asarray(noise, dtype=np.float64).reshape(-1, 2))
        if nz.shape[0] != r.shape[0]:
            raise InputError(f"refine_stem_map: noise has {nz.shape[0]} rows, not {r.shape[0]}.")
        s_r = np.sqrt(sigma_range**2 + nz[:, 0] ** 2)
        s_b = np.sqrt(sigma_bearing**2 + nz[:, 1] ** 2)
    R = world_observation_covariance(
        p[frame],
        S.reshape(-1, 3, 3)[frame],
        r,
        b,
        sigma_range=s_r,
        sigma_bearing=s_b,
        sensor_offset=sensor_offset,
    )
    from stemmap.slam.tree_covariance import associate_per_frame

    j = associate_per_frame(stem_map.xy, z, frame, gate)
    # keep time order for the sequential filter
    out = kalman_refine_trees(z, R, j, len(stem_map), process_noise=process_noise)
    trees = []
    for k, t in enumerate(stem_map.trees):
        if out.n_obs[k] > 0:
            trees.append(
                replace(
                    t,
                    x=float(out.xy[k, 0]),
                    y=float(out.xy[k, 1]),
                    cov=out.cov[k],
                    n_obs=int(out.n_obs[k]),
                )
            )
        else:
            trees.append(t)
    return StemMap(tuple(trees), frame=stem_map.frame, crs=stem_map.crs)
