"""Tree database front-end (visual-lidar T-SLAM paper, §2.5).

The tree DB stores, per tree, a position in the map frame, a diameter and a recognition count.
A tree seen in a frame is "the same tree" as a stored one when it falls within a gate of it; its
position and diameter are then updated by the count-weighted average of eq. (2) and the count is
incremented; otherwise it becomes a new entry. Entries whose count reaches a threshold (paper: 20)
are promoted to *landmarks*; only landmarks make the published tree map.

The back-end that runs the DB over a drive, :class:`TreeDbSlam` (registered as ``"treedb"``), lives
in :mod:`stemmap.slam._treedb_slam` and is importable from here; it is loaded on first access
(PEP 562 module ``__getattr__``) because it imports this module.

References
----------
.. [VL] "Visual LiDAR Odometry Using Tree Trunk Detection and LiDAR Localization",
   §2.5 "Tree trunks as T-SLAM landmarks", eq. (2); ../shared/papers/visual-lidar-odometry-...md
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.errors import ConfigError, InputError
from stemmap.types import FloatArray, StemMap, Tree, wrap_angle

if TYPE_CHECKING:  # pragma: no cover
    from stemmap.slam._treedb_slam import TreeDbSlam

__all__ = [
    "PRESETS",
    "TreeDb",
    "TreeDbConfig",
    "TreeDbSlam",
    "range_bearing_jacobians",
    "treedb_from_detections",
    "treedb_update",
]

IntArray = NDArray[np.int64]


# --------------------------------------------------------------------------------------------
# Observation model Jacobians shared by the slam-extra back-ends
# --------------------------------------------------------------------------------------------


def range_bearing_jacobians(
    poses: ArrayLike,
    landmarks: ArrayLike,
    sensor_offset: tuple[float, float] = (0.0, 0.0),
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Predicted range-bearing and its Jacobians, vectorised over any leading shape.

    Observation model of :mod:`stemmap.slam.base` (sensor at ``(a, b)`` in the vehicle frame)::

        s = p + R(θ) (a, b),  d = m - s,  r = |d|,  φ = atan2(d_y, d_x) - θ

    Parameters
    ----------
    poses : ndarray (..., 3)
        Vehicle poses (broadcast against ``landmarks``).
    landmarks : ndarray (..., 2)
    sensor_offset : (a, b), m

    Returns
    -------
    z : ndarray (..., 2)
        Predicted (range, bearing), bearing wrapped to (-pi, pi].
    H_x : ndarray (..., 2, 3)
        d z / d (x, y, θ).
    H_m : ndarray (..., 2, 2)
        d z / d m.
    """
    p = np.asarray(poses, dtype=np.float64)
    m = np.asarray(landmarks, dtype=np.float64)
    a, b = float(sensor_offset[0]), float(sensor_offset[1])
    c, s = np.cos(p[..., 2]), np.sin(p[..., 2])
    dsx = -a * s - b * c  # d s_x / d θ
    dsy = a * c - b * s
    dx = m[..., 0] - (p[..., 0] + a * c - b * s)
    dy = m[..., 1] - (p[..., 1] + a * s + b * c)
    q = np.maximum(dx * dx + dy * dy, 1e-12)
    r = np.sqrt(q)
    shape = np.broadcast_shapes(dx.shape)
    z = np.empty((*shape, 2))
    z[..., 0] = r
    z[..., 1] = wrap_angle(np.arctan2(dy, dx) - p[..., 2])
    H_m = np.empty((*shape, 2, 2))
    H_m[..., 0, 0] = dx / r
    H_m[..., 0, 1] = dy / r
    H_m[..., 1, 0] = -dy / q
    H_m[..., 1, 1] = dx / q
    H_x = np.empty((*shape, 2, 3))
    H_x[..., :, :2] = -H_m
    H_x[..., 0, 2] = -(dx * dsx + dy * dsy) / r
    H_x[..., 1, 2] = (dy * dsx - dx * dsy) / q - 1.0
    return z, H_x, H_m


# --------------------------------------------------------------------------------------------
# The tree DB (pure functions on an immutable columnar record)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TreeDbConfig:
    """Parameters of the tree DB.

    Parameters
    ----------
    gate : float, metres, > 0
        A detection within this distance of a stored tree is the same tree. The paper gives no
        value for this "specific range"; we use 0.5 m, the one distance §2.3/§2.5 do give (the
        median-filter radius), see docs/algorithms/slam-frontends.md.
    promote_count : int, >= 1
        Recognition count at which a tree becomes a landmark (paper: 20).
    """

    gate: float = 0.5
    promote_count: int = 20

    def __post_init__(self) -> None:
        if not (math.isfinite(self.gate) and self.gate > 0):
            raise ConfigError(
                f"TreeDbConfig.gate must be a positive distance in m, got {self.gate}."
            )
        if int(self.promote_count) < 1:
            raise ConfigError(f"TreeDbConfig.promote_count must be >= 1, got {self.promote_count}.")


#: Published parameter sets. ``"visual_lidar"``: the paper's count threshold 20 and our 0.5 m gate.
PRESETS: dict[str, TreeDbConfig] = {
    "visual_lidar": TreeDbConfig(gate=0.5, promote_count=20),
}


def _empty_f(n: int = 0) -> FloatArray:
    return np.zeros(n, dtype=np.float64)


@dataclass(frozen=True, eq=False)
class TreeDb:
    """Columnar tree database: N entries.

    Attributes
    ----------
    xy : ndarray of shape (N, 2), metres, map frame
    diameter : ndarray of shape (N,), metres (NaN until a diameter was measured)
    count : ndarray of shape (N,), int -- recognition count c_t of eq. (2)
    diameter_count : ndarray of shape (N,), int -- detections that carried a diameter
    sq_dev : ndarray of shape (N,), m^2 -- running sum of squared deviations of the position
        updates (Welford), for a per-tree scatter covariance
    first_time, last_time : ndarray of shape (N,), seconds
    """

    xy: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))
    diameter: FloatArray = field(default_factory=_empty_f)
    count: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    diameter_count: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    sq_dev: FloatArray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    first_time: FloatArray = field(default_factory=_empty_f)
    last_time: FloatArray = field(default_factory=_empty_f)

    def __len__(self) -> int:
        return int(self.xy.shape[0])

    def landmarks(self, promote_count: int) -> IntArray:
        """Indices of the entries promoted to landmarks (count >= ``promote_count``)."""
        return np.flatnonzero(self.count >= promote_count).astype(np.int64)

    def to_stem_map(self, promote_count: int = 1, *, frame: str = "map") -> StemMap:
        """The promoted entries as a :class:`~stemmap.types.StemMap`.

        Tree covariance is the scatter of the averaged detections divided by their number
        (standard error of the mean), floored at 1 cm^2 /n so a single sighting is not certain:
        the DB's own, for the localisation gate; :class:`TreeDbSlam` reports the pose-propagated
        one of :mod:`stemmap.slam.tree_covariance` instead.
        """
        idx = self.landmarks(promote_count)
        trees = []
        for new_id, i in enumerate(idx):
            n = int(self.count[i])
            cov = self.sq_dev[i] / max(n - 1, 1) / n + np.eye(2) * (1e-4 / n)
            trees.append(
                Tree(
                    id=new_id,
                    x=float(self.xy[i, 0]),
                    y=float(self.xy[i, 1]),
                    diameter=float(self.diameter[i]),
                    cov=cov,
                    n_obs=n,
                    first_time=float(self.first_time[i]),
                    last_time=float(self.last_time[i]),
                )
            )
        return StemMap(tuple(trees), frame=frame)


def treedb_update(
    db: TreeDb,
    xy: ArrayLike,
    diameters: ArrayLike | None = None,
    time: float = 0.0,
    *,
    gate: float = 0.5,
    known: ArrayLike | None = None,
    candidates: ArrayLike | None = None,
) -> tuple[TreeDb, IntArray]:
    """Add one frame of detections (map frame) to the tree DB, visual-lidar paper §2.5.

    Each detection is matched to the nearest stored tree within ``gate`` (one detection per tree
    and frame, closest pairs first); a match updates the stored tree with the count-weighted
    average of eq. (2)

    .. math::
        x_t = (c_{t-1} x_{t-1} + x) / (c_{t-1} + 1),\\quad
        y_t = (c_{t-1} y_{t-1} + y) / (c_{t-1} + 1),\\quad c_t = c_{t-1} + 1,

    and the diameter the same way (over the detections that carry one); an unmatched detection
    becomes a new entry with count 1.

    Parameters
    ----------
    db : TreeDb
        Current database (not modified).
    xy : ndarray of shape (K, 2), metres
        Detections of one frame in the map frame.
    diameters : ndarray of shape (K,), metres, optional
        NaN where unknown.
    time : float, seconds
    gate : float, metres, > 0
    known : ndarray of shape (K,), int, optional
        Association already decided elsewhere (e.g. by the localisation's Mahalanobis gate, which
        scales with range): DB index per detection, -1 = decide here by ``gate``.
    candidates : ndarray of shape (N,), bool, optional
        Entries the ``gate`` may match (default: all), e.g. only the recently seen ones when an
        older part of the map is left to loop closure.

    Returns
    -------
    db : TreeDb
        The updated database (new arrays).
    index : ndarray of shape (K,), int
        DB entry each detection went to.

    Raises
    ------
    InputError
        If ``xy`` is not (K, 2) finite or ``diameters`` has the wrong length.

    Examples
    --------
    >>> db, idx = treedb_update(TreeDb(), [[0.0, 0.0]], [0.3])
    >>> db, idx = treedb_update(db, [[0.2, 0.0], [5.0, 5.0]], [0.5, 0.2])
    >>> idx.tolist(), db.xy[0].tolist(), db.count.tolist()
    ([0, 1], [0.1, 0.0], [2, 1])
    """
    z = np.asarray(xy, dtype=np.float64)
    if z.size == 0:
        z = z.reshape(0, 2)
    if z.ndim != 2 or z.shape[1] != 2:
        raise InputError(f"treedb_update: detections must have shape (K, 2), got {z.shape}.")
    if not np.all(np.isfinite(z)):
        raise InputError("treedb_update: detection positions must be finite (got NaN or inf).")
    k = z.shape[0]
    d = (
        np.full(k, np.nan)
        if diameters is None
        else np.asarray(diameters, dtype=np.float64).reshape(-1)
    )
    if d.shape[0] != k:
        raise InputError(f"treedb_update: {k} detections but {d.shape[0]} diameters.")
    if not gate > 0:
        raise ConfigError(f"treedb_update: gate must be > 0 m, got {gate}.")
    n = len(db)
    assoc = np.full(k, -1, dtype=np.int64)
    if known is not None:
        kn = np.asarray(known, dtype=np.int64).reshape(-1)
        if kn.shape[0] != k or np.any(kn >= n):
            raise InputError(
                f"treedb_update: known must hold {k} DB indices below {n}, got shape {kn.shape}."
            )
        assoc[:] = np.where(kn >= 0, kn, -1)
    if n and k:
        sub = np.arange(n)
        if candidates is not None:
            ok_t = np.asarray(candidates, dtype=bool).reshape(-1)
            if ok_t.shape[0] != n:
                raise InputError(f"treedb_update: candidates must have {n} entries.")
            sub = np.flatnonzero(ok_t)
        txy = db.xy[sub]
        dist = np.hypot(z[:, None, 0] - txy[None, :, 0], z[:, None, 1] - txy[None, :, 1])
        # Greedy one-to-one: closest pairs first (a tree is seen at most once per frame).
        cand = np.argwhere(dist <= gate)
        if cand.size:
            order = np.argsort(dist[cand[:, 0], cand[:, 1]], kind="stable")
            used_t = np.zeros(n, dtype=bool)
            used_t[assoc[assoc >= 0]] = True
            for i, jl in cand[order]:
                j = sub[jl]
                if assoc[i] < 0 and not used_t[j]:
                    assoc[i] = j
                    used_t[j] = True
    xy_new = db.xy.copy()
    dia = db.diameter.copy()
    cnt = db.count.copy()
    dcnt = db.diameter_count.copy()
    sq = db.sq_dev.copy()
    last = db.last_time.copy()
    m = assoc >= 0
    if np.any(m):
        j = assoc[m]
        c = cnt[j].astype(np.float64)
        delta = z[m] - xy_new[j]
        xy_new[j] = (c[:, None] * xy_new[j] + z[m]) / (c[:, None] + 1.0)  # eq. (2)
        delta2 = z[m] - xy_new[j]
        sq[j] += delta[:, :, None] * delta2[:, None, :]  # Welford scatter
        cnt[j] += 1
        last[j] = time
        dm = m & np.isfinite(d)
        if np.any(dm):
            jd = assoc[dm]
            cd = dcnt[jd].astype(np.float64)
            prev = np.where(cd > 0, dia[jd], 0.0)
            dia[jd] = (cd * prev + d[dm]) / (cd + 1.0)
            dcnt[jd] += 1
    new = ~m
    n_new = int(np.count_nonzero(new))
    if n_new:
        assoc[new] = np.arange(n, n + n_new)
        xy_new = np.vstack((xy_new, z[new]))
        dia = np.concatenate((dia, d[new]))
        cnt = np.concatenate((cnt, np.ones(n_new, dtype=np.int64)))
        dcnt = np.concatenate((dcnt, np.isfinite(d[new]).astype(np.int64)))
        sq = np.concatenate((sq, np.zeros((n_new, 2, 2))))
        last = np.concatenate((last, np.full(n_new, time)))
        first = np.concatenate((db.first_time, np.full(n_new, time)))
    else:
        first = db.first_time
    return TreeDb(xy_new, dia, cnt, dcnt, sq, first, last), assoc


def treedb_from_detections(
    xy: ArrayLike,
    diameters: ArrayLike,
    times: ArrayLike,
    entry: ArrayLike,
    n_entries: int,
) -> TreeDb:
    """The tree DB that eq. (2) builds from these detections and this association.

    Eq. (2)'s count-weighted running average of a tree's detections is their plain mean, so
    re-mapping the detections (e.g. from relaxed poses after a loop closure) and averaging per
    entry gives exactly the database the updates would have built at those poses. Entries
    without detections (merged into another) get count 0 and position NaN.

    Parameters
    ----------
    xy : ndarray (K, 2), m -- detections in the map frame
    diameters : ndarray (K,), m (NaN = unknown)
    times : ndarray (K,), s
    entry : ndarray (K,), int -- DB entry of each detection (-1 = none)
    n_entries : int
    """
    z = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    d = np.asarray(diameters, dtype=np.float64).reshape(-1)
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    e = np.asarray(entry, dtype=np.int64).reshape(-1)
    ok = e >= 0
    z, d, t, e = z[ok], d[ok], t[ok], e[ok]
    n = int(n_entries)
    cnt = np.bincount(e, minlength=n)
    c = np.maximum(cnt, 1).astype(np.float64)
    mean = np.column_stack([np.bincount(e, weights=z[:, i], minlength=n) / c for i in range(2)])
    mean[cnt == 0] = np.nan
    dev = z - mean[e]
    sq = np.zeros((n, 2, 2))
    for a in range(2):
        for b in range(2):
            sq[:, a, b] = np.bincount(e, weights=dev[:, a] * dev[:, b], minlength=n)
    fin = np.isfinite(d)
    dcnt = np.bincount(e[fin], minlength=n)
    dsum = np.bincount(e[fin], weights=d[fin], minlength=n)
    dia = np.where(dcnt > 0, dsum / np.maximum(dcnt, 1), np.nan)
    first = np.full(n, np.inf)
    np.minimum.at(first, e, t)
    last = np.full(n, -np.inf)
    np.maximum.at(last, e, t)
    return TreeDb(mean, dia, cnt.astype(np.int64), dcnt.astype(np.int64), sq, first, last)


def __getattr__(name: str) -> Any:
    """Lazy re-export of :class:`~stemmap.slam._treedb_slam.TreeDbSlam` (it imports this module)."""
    if name == "TreeDbSlam":
        from stemmap.slam._treedb_slam import TreeDbSlam

        return TreeDbSlam
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | {"TreeDbSlam"})
