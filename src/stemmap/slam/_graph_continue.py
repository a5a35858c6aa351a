"""Continuing a saved session graph in a later session of the iSAM2 back-end (ours).

A map directory written by ``stemmap map`` (isam2) also carries the session's factor graph,
``graph.npz`` (:func:`write_graph`): its keyframe sensor poses and trees at the optimum and
every factor between them -- odometry ``BetweenFactorPose2`` (measured increment and
covariance), ``BearingRangeFactor2D`` (bearing, range and their sigmas; the robust kernel is
the continuing session's ``Isam2Config.robust``) and the pose priors (the gauge prior on the
first keyframe, the anchors of :func:`~stemmap.slam._graph_revisits.anchor_prior`). The format
is an explicit factor list in a NumPy archive (no pickle), versioned by ``format_version``;
GTSAM's ``NonlinearFactorGraph.serialize()`` (a Boost text archive) was not used: it would tie
the file to one GTSAM build, cannot carry our tree ids, and gives no field to validate
before handing it to C++.

A later session relocalised in that map (:func:`stemmap.slam.relocalise.continue_session`,
unchanged, from an unknown start) *continues* the graph (:class:`ContinuedGraph`): the earlier
poses enter as variables ``W(i)`` and the earlier trees as the landmarks ``L(0..n-1)`` the
prior map gives them anyway, with all their factors, so this session's observations update
the earlier trees *and poses* through the graph (the single-run smoothing), instead of
holding the trees by a marginal prior (:func:`~stemmap.slam.relocalise.prior_tree_factors`),
which fixes what the earlier session knew about them at its end. The new session's first
keyframe is tied to the earlier graph only through the trees it re-observes (plus the loose
``reloc_prior_sigmas`` prior at the relocalised pose that also keeps the first iSAM2 update
well posed): no odometry links the two sessions (the start is unknown). ``W`` sorts before
``X``, so the keyframe chain of the pose marginals is the earlier poses followed by this
session's (:func:`stemmap.slam._graph_marginals._chain_blocks`).

This is the smoothing formulation of multi-session SLAM: one graph over all sessions, the
sessions linked by shared landmarks (McDonald, Kaess, Cadena, Neira & Leonard 2013,
"Real-time 6-DOF multi-session visual SLAM over large-scale environments", Robotics and
Autonomous Systems 61(10), with anchor nodes; here the relocalisation puts the new session
in the earlier frame, so no anchor variable is needed). docs/algorithms/slam.md "Continuing
the saved graph".
"""

from __future__ import annotations

import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from stemmap.errors import InputError
from stemmap.types import FloatArray, StemMap

__all__ = [
    "GRAPH_FORMAT",
    "GRAPH_NPZ",
    "GRAPH_VERSION",
    "ContinuedGraph",
    "SavedGraph",
    "export_graph",
    "read_graph",
    "write_graph",
]

#: File name of the session graph beside trees.csv (``stemmap map``, isam2).
GRAPH_NPZ = "graph.npz"
#: ``format`` field of the archive and its version (bumped on any change of the arrays).
GRAPH_FORMAT = "stemmap-isam2-graph"
GRAPH_VERSION = 1


@dataclass(frozen=True)
class SavedGraph:
    """A session's factor graph at its optimum (shapes: P poses, N trees, E odometry factors,
    M tree measurements, Q pose priors; poses are **sensor** poses, map frame, m / rad).

    poses : (P, 3) x, y, theta
    tree_ids : (N,) int64, the ``id`` column of trees.csv of each tree row
    trees : (N, 2) x, y
    odo_ij : (E, 2) int64 pose rows (i, j) of ``BetweenFactorPose2(i, j)``
    odo_delta : (E, 3) measured increment; odo_cov : (E, 3, 3) its covariance
    meas_pose, meas_tree : (M,) int64 pose row and tree row of each bearing-range factor
    meas : (M, 4) bearing (rad), range (m), sigma_bearing (rad), sigma_range (m)
    prior_pose : (Q,) int64 pose rows with a ``PriorFactorPose2``; prior_mean : (Q, 3);
    prior_cov : (Q, 3, 3)
    """

    poses: FloatArray
    tree_ids: np.ndarray
    trees: FloatArray
    odo_ij: np.ndarray
    odo_delta: FloatArray
    odo_cov: FloatArray
    meas_pose: np.ndarray
    meas_tree: np.ndarray
    meas: FloatArray
    prior_pose: np.ndarray
    prior_mean: FloatArray
    prior_cov: FloatArray

    @property
    def n_poses(self) -> int:
        return int(self.poses.shape[0])

    def __post_init__(self) -> None:
        problem = _shape_problem(self)
        if problem:
            raise InputError(f"session graph: {problem}.")


_FIELDS = (
    "poses", "tree_ids", "trees", "odo_ij", "odo_delta", "odo_cov", "meas_pose", "meas_tree",
    "meas", "prior_pose", "prior_mean", "prior_cov",
)  # fmt: skip
_INT_FIELDS = {"tree_ids", "odo_ij", "meas_pose", "meas_tree", "prior_pose"}


def _shape_problem(g: SavedGraph) -> str:
    """What is wrong with the arrays of ``g`` ('' when nothing)."""
    p, n = g.poses.shape[0], g.trees.shape[0]
    e, m, q = g.odo_ij.shape[0], g.meas_pose.shape[0], g.prior_pose.shape[0]
    want = {
        "poses": (p, 3), "tree_ids": (n,), "trees": (n, 2), "odo_ij": (e, 2),
        "odo_delta": (e, 3), "odo_cov": (e, 3, 3), "meas_pose": (m,), "meas_tree": (m,),
        "meas": (m, 4), "prior_pose": (q,), "prior_mean": (q, 3), "prior_cov": (q, 3, 3),
    }  # fmt: skip
    for name, shape in want.items():
        a = getattr(g, name)
        if a.shape != shape:
            return f"{name} has shape {a.shape}, expected {shape}"
        if name not in _INT_FIELDS and not np.isfinite(a).all():
            return f"{name} has non-finite values"
    for name, hi in (("odo_ij", p), ("meas_pose", p), ("prior_pose", p), ("meas_tree", n)):
        a = getattr(g, name)
        if a.size and (a.min() < 0 or a.max() >= hi):
            return f"{name} indexes outside 0..{hi - 1}"
    if p and q == 0:
        return "no pose prior (the graph has no gauge)"
    if m and (g.meas[:, 2:] <= 0).any():
        return "measurement sigmas must be > 0"
    for name in ("odo_cov", "prior_cov"):
        a = getattr(g, name)
        if a.size and np.linalg.eigvalsh(0.5 * (a + a.transpose(0, 2, 1))).min() <= 0:
            return f"{name} has a covariance that is not positive definite"
    if np.unique(g.tree_ids).size != n:
        return "tree_ids are not unique"
    return ""


def write_graph(path: str | Path, graph: SavedGraph) -> None:
    """Write ``graph`` as ``graph.npz`` (atomically; arrays of :class:`SavedGraph` plus
    ``format`` and ``format_version``)."""
    from stemmap.io.atomic import atomic_write

    arrays = {k: getattr(graph, k) for k in _FIELDS}
    with atomic_write(path, "wb") as fh:
        np.savez_compressed(
            fh, format=np.array(GRAPH_FORMAT), format_version=np.array(GRAPH_VERSION), **arrays
        )


def read_graph(path: str | Path, stem_map: StemMap | None = None) -> SavedGraph:
    """Read a :func:`write_graph` archive; with ``stem_map`` (the trees.csv beside it) also
    check that its trees are that map's (same ids).

    Raises
    ------
    InputError
        Unreadable file, another format or version, missing arrays, wrong shapes or
        indices, non-finite values, or tree ids other than the map's.
    """
    p = Path(path)
    where = f"session graph {str(p)!r}"
    try:
        with np.load(p, allow_pickle=False) as z:
            fmt, ver = str(z["format"]), int(z["format_version"])
            if fmt != GRAPH_FORMAT or ver != GRAPH_VERSION:
                raise InputError(
                    f"{where} is format {fmt!r} version {ver}; this stemmap reads "
                    f"{GRAPH_FORMAT!r} version {GRAPH_VERSION}. Map the earlier session again "
                    f"with this version, or delete {p.name} to continue from the marginal prior."
                )
            arrays: dict[str, Any] = {
                k: np.asarray(z[k], dtype=np.int64 if k in _INT_FIELDS else np.float64)
                for k in _FIELDS
            }
    except InputError:
        raise
    except FileNotFoundError as exc:
        raise InputError(f"{where} does not exist.") from exc
    except (OSError, ValueError, KeyError, TypeError, EOFError, zipfile.BadZipFile) as exc:
        raise InputError(
            f"{where} is damaged or not a stemmap graph ({type(exc).__name__}: {exc}); delete "
            f"{p.name} to continue from the marginal prior (trees.csv)."
        ) from exc
    try:
        g = SavedGraph(**arrays)
    except InputError as exc:
        raise InputError(f"{where}: {exc}; delete {p.name} to use the marginal prior.") from exc
    if stem_map is not None:
        ids = np.array([int(t.id) for t in stem_map], dtype=np.int64)
        if ids.size != g.tree_ids.size or not np.array_equal(np.sort(ids), np.sort(g.tree_ids)):
            raise InputError(
                f"{where} holds {g.tree_ids.size} trees whose ids differ from the {ids.size} "
                "trees of the trees CSV beside it (written by another run?); rewrite both with "
                f"one `stemmap map` run, or delete {p.name} to use the marginal prior."
            )
    return g


class ContinuedGraph:
    """A saved graph continued by the current session: pose rows become ``W(i)``, tree rows
    the landmark slots ``slot[row]`` (the prior map's tree order); see the module docs.

    ``factors`` / ``values`` give what enters the graph; ``factors(alias=...)`` re-keys the
    measurements of merged trees onto their representative (duplicate merging,
    :func:`stemmap.slam._graph_batch.batch_rounds`).
    """

    def __init__(
        self,
        saved: SavedGraph,
        prior_map: StemMap,
        wkey: Callable[[int], int],
        inflation: float = 1.0,
    ) -> None:
        pos = {int(t.id): j for j, t in enumerate(prior_map)}
        missing = [int(i) for i in saved.tree_ids if int(i) not in pos]
        if missing:
            raise InputError(
                f"session graph: {len(missing)} of its trees (e.g. id {missing[0]}) are not in "
                "the prior map."
            )
        self.saved = saved
        self.slot = np.array([pos[int(i)] for i in saved.tree_ids], dtype=np.int64)
        self.n_poses = saved.n_poses
        self.wkey = wkey
        # the odometry and measurement covariances x inflation (the gauge prior as saved)
        self.inflation = float(inflation)

    def tree_xy(self, n_prior: int) -> FloatArray:
        """(n_prior, 2) positions of the prior map's trees from the graph (NaN: not in it)."""
        out = np.full((n_prior, 2), np.nan)
        out[self.slot] = self.saved.trees
        return out

    def values(self, gtsam: Any, current: Any = None) -> list[tuple[int, Any]]:
        """``(key, Pose2)`` of the earlier poses: at the saved optimum, or their estimate in
        ``current`` (a ``gtsam.Values``)."""
        if current is not None:
            return [(self.wkey(i), current.atPose2(self.wkey(i))) for i in range(self.n_poses)]
        return [(self.wkey(i), gtsam.Pose2(*map(float, q))) for i, q in enumerate(self.saved.poses)]

    def pose_factors(self, gtsam: Any) -> list[Any]:
        """The saved odometry and pose priors on ``W(i)``."""
        g, wkey = self.saved, self.wkey
        out: list[Any] = []
        for (i, j), d, c in zip(g.odo_ij.tolist(), g.odo_delta, g.odo_cov, strict=True):
            out.append(
                gtsam.BetweenFactorPose2(
                    wkey(i),
                    wkey(j),
                    gtsam.Pose2(*map(float, d)),
                    gtsam.noiseModel.Gaussian.Covariance(np.asarray(c) * self.inflation),
                )
            )
        for i, m, c in zip(g.prior_pose.tolist(), g.prior_mean, g.prior_cov, strict=True):
            out.append(
                gtsam.PriorFactorPose2(
                    wkey(i),
                    gtsam.Pose2(*map(float, m)),
                    gtsam.noiseModel.Gaussian.Covariance(np.asarray(c)),
                )
            )
        return out

    def factors(
        self,
        gtsam: Any,
        lkey: Callable[[int], int],
        meas_noise: Callable[[FloatArray], Any],
        alias: np.ndarray | None = None,
    ) -> list[Any]:
        """Every saved factor: :meth:`pose_factors`, then the bearing-range factors on
        ``W(i)`` / ``L(slot)``; ``alias`` maps a landmark slot to the slot its factors now
        point to (merged trees)."""
        g, f = self.saved, np.sqrt(self.inflation)
        slots = self.slot[g.meas_tree]
        if alias is not None:
            slots = np.asarray(alias, dtype=np.int64)[slots]
        return self.pose_factors(gtsam) + [
            gtsam.BearingRangeFactor2D(
                self.wkey(i), lkey(j), gtsam.Rot2(b), r, meas_noise(np.array([sb, sr]) * f)
            )
            for i, j, (b, r, sb, sr) in zip(
                g.meas_pose.tolist(), slots.tolist(), g.meas.tolist(), strict=True
            )
        ]


def _gaussian_cov(noise: Any) -> FloatArray:
    """Covariance of a GTSAM Gaussian noise model (a robust one: of its base)."""
    base = noise.noise() if hasattr(noise, "noise") else noise
    return np.asarray(base.covariance(), dtype=np.float64)


def export_graph(
    gtsam: Any,
    values: Any,
    *,
    keys: tuple[Callable[[int], int], Callable[[int], int], Callable[[int], int]],
    gk: np.ndarray,
    keep: np.ndarray,
    alias: np.ndarray,
    odo_fac: list[Any],
    pose_priors: list[Any],
    meas_rec: list[tuple[int, int, float, float, float, float]],
    cont: ContinuedGraph | None,
) -> SavedGraph:
    """The session graph at ``values`` as a :class:`SavedGraph`: the continued earlier graph
    (``cont``: its poses first, then this session's graph keyframes ``gk``), the kept trees
    ``keep`` (tree id = landmark slot, as in trees.csv), the odometry factors ``odo_fac`` and
    pose priors ``pose_priors`` (``BetweenFactorPose2`` / ``PriorFactorPose2`` on ``W`` / ``X``
    keys), and the measurements ``meas_rec`` (keyframe, slot, bearing, range, sigmas) on kept
    trees (after merging: on ``alias[slot]``). Measurements of trees that are not kept (fewer
    than ``min_obs`` observations, not in trees.csv) are dropped with them."""
    XK, LK, WK = keys
    n_w = 0 if cont is None else cont.n_poses
    row_of: dict[int, int] = {}
    poses = []
    for i in range(n_w):
        p = values.atPose2(WK(i))
        row_of[WK(i)] = i
        poses.append((p.x(), p.y(), p.theta()))
    for r_k, k in enumerate(gk.tolist()):
        p = values.atPose2(XK(k))
        row_of[XK(k)] = n_w + r_k
        poses.append((p.x(), p.y(), p.theta()))
    tree_row = np.full(int(alias.size), -1, dtype=np.int64)
    tree_row[keep] = np.arange(keep.size)
    trees = np.array([values.atPoint2(LK(int(j))) for j in keep.tolist()]).reshape(-1, 2)
    odo_ij: list[Any] = []
    odo_d: list[Any] = []
    odo_c: list[Any] = []
    pri_i: list[Any] = []
    pri_m: list[Any] = []
    pri_c: list[Any] = []
    if cont is not None:  # the earlier graph's pose factors, as saved (pose rows unchanged)
        g0 = cont.saved
        odo_ij, odo_d, odo_c = list(g0.odo_ij), list(g0.odo_delta), list(g0.odo_cov)
        pri_i, pri_m, pri_c = list(g0.prior_pose), list(g0.prior_mean), list(g0.prior_cov)
    for f in list(odo_fac) + list(pose_priors):
        ks = [int(k) for k in f.keys()]  # noqa: SIM118 (a GTSAM factor, not a dict)
        if isinstance(f, gtsam.BetweenFactorPose2):
            m = f.measured()
            odo_ij.append((row_of[ks[0]], row_of[ks[1]]))
            odo_d.append((m.x(), m.y(), m.theta()))
            odo_c.append(_gaussian_cov(f.noiseModel()))
        else:
            m = f.prior()
            pri_i.append(row_of[ks[0]])
            pri_m.append((m.x(), m.y(), m.theta()))
            pri_c.append(_gaussian_cov(f.noiseModel()))
    mp, mt, mm = [], [], []
    if cont is not None:
        g = cont.saved
        rows = tree_row[alias[cont.slot[g.meas_tree]]]
        ok = rows >= 0
        mp.extend(g.meas_pose[ok].tolist())
        mt.extend(rows[ok].tolist())
        mm.extend(g.meas[ok].tolist())
    for k, j, brg, rng, sb, sr in meas_rec:
        t = int(tree_row[alias[j]])
        if t >= 0:
            mp.append(row_of[XK(k)])
            mt.append(t)
            mm.append([brg, rng, sb, sr])
    return SavedGraph(
        poses=np.asarray(poses, dtype=np.float64).reshape(-1, 3),
        tree_ids=np.asarray(keep, dtype=np.int64),
        trees=np.asarray(trees, dtype=np.float64),
        odo_ij=np.asarray(odo_ij, dtype=np.int64).reshape(-1, 2),
        odo_delta=np.asarray(odo_d, dtype=np.float64).reshape(-1, 3),
        odo_cov=np.asarray(odo_c, dtype=np.float64).reshape(-1, 3, 3),
        meas_pose=np.asarray(mp, dtype=np.int64),
        meas_tree=np.asarray(mt, dtype=np.int64),
        meas=np.asarray(mm, dtype=np.float64).reshape(-1, 4),
        prior_pose=np.asarray(pri_i, dtype=np.int64),
        prior_mean=np.asarray(pri_m, dtype=np.float64).reshape(-1, 3),
        prior_cov=np.asarray(pri_c, dtype=np.float64).reshape(-1, 3, 3),
    )


def graph_stats(cont: ContinuedGraph | None) -> dict[str, int | float]:
    """Run statistics of the continued graph (empty without one)."""
    if cont is None:
        return {}
    g = cont.saved
    return {
        "continued_poses": g.n_poses,
        "continued_trees": int(g.trees.shape[0]),
        "continued_factors": int(g.odo_ij.shape[0] + g.meas_pose.shape[0] + g.prior_pose.shape[0]),
    }
