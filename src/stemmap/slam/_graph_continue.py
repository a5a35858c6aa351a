"""Continuing a saved session graph in a later session of the iSAM2 back-end (ours).

A map directory written by ``stemmap map`` (isam2) also carries the session's factor graph,
``graph.npz`` (:func:`write_graph`): its keyframe sensor poses and trees at the optimum and
every factor between them -- odometry ``BetweenFactorPose2`` (measured increment and
covariance), ``BearingRangeFactor2D`` (bearing, range and their sigmas; the robust kernel is
the continuing session's ``Isam2Config.robust``) and the pose priors (the gauge prior on the
first keyframe, the anchors of :func:`~stemmap.slam._graph_revisits.anchor_prior`); since
format 2 also what held a session's frame or its earlier map, so that GNSS runs and runs on a
marginal prior write theirs too: the GNSS fixes (:mod:`stemmap.slam.gnss`: antenna pose,
its between factor to the keyframe, its robust position prior), the prior map's per-tree
priors (mean, covariance, robust kernel) or its joint prior (``U``, ``UᵀU`` the joint
information). The format is an explicit factor list in a NumPy archive (no pickle),
versioned by ``format_version`` (version 1 files, without the format-2 arrays, are read);
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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from stemmap.errors import InputError
from stemmap.io._util import check_npz_sizes
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
#: ``format`` field of the archive and its version (bumped on any change of the arrays;
#: version 2 added the GNSS fixes and the prior map's tree priors, version 1 is still read).
GRAPH_FORMAT = "stemmap-isam2-graph"
GRAPH_VERSION = 2
_READ_VERSIONS = (1, 2)
#: robust kernels a saved prior may name (:func:`stemmap.slam.gnss.robust_kernel`)
_KERNELS = ("none", "huber", "cauchy")


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

    Format 2 (empty when absent; K tree priors, J trees of a joint prior, G GNSS fixes):

    tprior_tree : (K,) int64 tree rows; tprior_mean : (K, 2); tprior_cov : (K, 2, 2);
    tprior_robust : their kernel ("none", "huber", "cauchy") of width tprior_robust_k sigmas
    joint_tree : (J,) int64 tree rows (repeats: merged trees); joint_mean : (J, 2);
    joint_sqrt : (2J, 2J) ``U`` of the factor ``‖U (x - joint_mean)‖²``
    fix_pose : (G,) int64 keyframe pose rows; fix_rel : (G, 3) keyframe -> antenna pose and
    fix_rel_cov : (G, 3, 3) its covariance; fix_antenna : (G, 3) antenna poses at the optimum;
    fix_xy : (G, 2) the fixes, fix_sigma : (G,) m; fix_robust / fix_robust_k their kernel
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
    tprior_tree: np.ndarray = field(default_factory=lambda: np.zeros((0,), dtype=np.int64))
    tprior_mean: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))
    tprior_cov: FloatArray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    tprior_robust: str = "none"
    tprior_robust_k: float = 1.0
    joint_tree: np.ndarray = field(default_factory=lambda: np.zeros((0,), dtype=np.int64))
    joint_mean: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))
    joint_sqrt: FloatArray = field(default_factory=lambda: np.zeros((0, 0)))
    fix_pose: np.ndarray = field(default_factory=lambda: np.zeros((0,), dtype=np.int64))
    fix_rel: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    fix_rel_cov: FloatArray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    fix_antenna: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    fix_xy: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))
    fix_sigma: FloatArray = field(default_factory=lambda: np.zeros((0,)))
    fix_robust: str = "none"
    fix_robust_k: float = 1.0

    @property
    def n_poses(self) -> int:
        return int(self.poses.shape[0])

    @property
    def n_fixes(self) -> int:
        return int(self.fix_pose.shape[0])

    @property
    def n_factors(self) -> int:
        """Factors of the graph (a joint prior counts one, a GNSS fix two)."""
        return int(
            self.odo_ij.shape[0] + self.meas_pose.shape[0] + self.prior_pose.shape[0]
            + self.tprior_tree.shape[0] + (self.joint_tree.shape[0] > 0) + 2 * self.n_fixes
        )  # fmt: skip

    def __post_init__(self) -> None:
        problem = _shape_problem(self)
        if problem:
            raise InputError(f"session graph: {problem}.")


_FIELDS = (
    "poses", "tree_ids", "trees", "odo_ij", "odo_delta", "odo_cov", "meas_pose", "meas_tree",
    "meas", "prior_pose", "prior_mean", "prior_cov",
)  # fmt: skip
#: the arrays format 2 added (optional when reading: a version-1 file has none)
_V2_FIELDS = (
    "tprior_tree", "tprior_mean", "tprior_cov", "joint_tree", "joint_mean", "joint_sqrt",
    "fix_pose", "fix_rel", "fix_rel_cov", "fix_antenna", "fix_xy", "fix_sigma",
)  # fmt: skip
_V2_SCALARS = {"tprior_robust": str, "tprior_robust_k": float, "fix_robust": str,
               "fix_robust_k": float}  # fmt: skip
_INT_FIELDS = {"tree_ids", "odo_ij", "meas_pose", "meas_tree", "prior_pose", "tprior_tree",
               "joint_tree", "fix_pose"}  # fmt: skip


def _shape_problem(g: SavedGraph) -> str:
    """What is wrong with the arrays of ``g`` ('' when nothing)."""
    p, n = g.poses.shape[0], g.trees.shape[0]
    e, m, q = g.odo_ij.shape[0], g.meas_pose.shape[0], g.prior_pose.shape[0]
    k, j, f = g.tprior_tree.shape[0], g.joint_tree.shape[0], g.fix_pose.shape[0]
    want = {
        "poses": (p, 3), "tree_ids": (n,), "trees": (n, 2), "odo_ij": (e, 2),
        "odo_delta": (e, 3), "odo_cov": (e, 3, 3), "meas_pose": (m,), "meas_tree": (m,),
        "meas": (m, 4), "prior_pose": (q,), "prior_mean": (q, 3), "prior_cov": (q, 3, 3),
        "tprior_tree": (k,), "tprior_mean": (k, 2), "tprior_cov": (k, 2, 2),
        "joint_tree": (j,), "joint_mean": (j, 2), "joint_sqrt": (2 * j, 2 * j),
        "fix_pose": (f,), "fix_rel": (f, 3), "fix_rel_cov": (f, 3, 3), "fix_antenna": (f, 3),
        "fix_xy": (f, 2), "fix_sigma": (f,),
    }  # fmt: skip
    for name, shape in want.items():
        a = getattr(g, name)
        if a.shape != shape:
            return f"{name} has shape {a.shape}, expected {shape}"
        if name not in _INT_FIELDS and not np.isfinite(a).all():
            return f"{name} has non-finite values"
    for name, hi in (("odo_ij", p), ("meas_pose", p), ("prior_pose", p), ("meas_tree", n),
                     ("tprior_tree", n), ("joint_tree", n), ("fix_pose", p)):  # fmt: skip
        a = getattr(g, name)
        if a.size and (a.min() < 0 or a.max() >= hi):
            return f"{name} indexes outside 0..{hi - 1}"
    if p and q == 0:
        return "no pose prior (the graph has no gauge)"
    if m and (g.meas[:, 2:] <= 0).any():
        return "measurement sigmas must be > 0"
    if f and (g.fix_sigma <= 0).any():
        return "GNSS fix sigmas must be > 0"
    for name in ("tprior_robust", "fix_robust"):
        if getattr(g, name) not in _KERNELS:
            return f"{name} is {getattr(g, name)!r}, not one of {', '.join(_KERNELS)}"
    for name in ("odo_cov", "prior_cov", "tprior_cov", "fix_rel_cov"):
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

    arrays: dict[str, Any] = {k: getattr(graph, k) for k in (*_FIELDS, *_V2_FIELDS)}
    arrays.update({k: np.array(getattr(graph, k)) for k in _V2_SCALARS})
    with atomic_write(path, "wb") as fh:
        np.savez_compressed(
            fh, format=np.array(GRAPH_FORMAT), format_version=np.array(GRAPH_VERSION),
            **arrays,
        )  # fmt: skip


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
            check_npz_sizes(z, p, "session graph")
            fmt, ver = str(z["format"]), int(z["format_version"])
            if fmt != GRAPH_FORMAT or ver not in _READ_VERSIONS:
                raise InputError(
                    f"{where} is format {fmt!r} version {ver}; this stemmap reads "
                    f"{GRAPH_FORMAT!r} versions {', '.join(map(str, _READ_VERSIONS))}. Map the "
                    f"earlier session again with this version, or delete {p.name} to continue "
                    "from the marginal prior."
                )
            arrays: dict[str, Any] = {
                k: np.asarray(z[k], dtype=np.int64 if k in _INT_FIELDS else np.float64)
                for k in (*_FIELDS, *(_V2_FIELDS if ver >= 2 else ()))
            }
            if ver >= 2:
                arrays.update({k: t(z[k][()]) for k, t in _V2_SCALARS.items()})
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
        vkey: Callable[[int], int] | None = None,
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
        if saved.n_fixes and vkey is None:
            raise ValueError("a saved graph with GNSS fixes needs vkey (the antenna poses).")
        self.vkey = vkey  # the GNSS antenna poses V(i) ('v' sorts before 'w': poses first)
        # every covariance x inflation but the pose priors' (the gauge and anchors as saved)
        self.inflation = float(inflation)

    def tree_xy(self, n_prior: int) -> FloatArray:
        """(n_prior, 2) positions of the prior map's trees from the graph (NaN: not in it)."""
        out = np.full((n_prior, 2), np.nan)
        out[self.slot] = self.saved.trees
        return out

    def values(self, gtsam: Any, current: Any = None) -> list[tuple[int, Any]]:
        """``(key, Pose2)`` of the earlier poses (and GNSS antenna poses): at the saved
        optimum, or their estimate in ``current`` (a ``gtsam.Values``)."""
        keys = [self.wkey(i) for i in range(self.n_poses)]
        keys += [self.vkey(i) for i in range(self.saved.n_fixes)] if self.vkey else []
        if current is not None:
            return [(k, current.atPose2(k)) for k in keys]
        rows = np.concatenate((self.saved.poses, self.saved.fix_antenna))
        return [(k, gtsam.Pose2(*map(float, q))) for k, q in zip(keys, rows, strict=True)]

    def pose_factors(self, gtsam: Any) -> list[Any]:
        """The saved odometry and pose priors on ``W(i)``, and the GNSS fixes (antenna poses
        ``V(i)``: between factor to their keyframe, robust position prior)."""
        from stemmap.slam.gnss import robust_kernel

        g, wkey = self.saved, self.wkey
        out: list[Any] = []
        kern = robust_kernel(gtsam, g.fix_robust, g.fix_robust_k)
        for i, (r, rel, c, xy, sg) in enumerate(
            zip(g.fix_pose.tolist(), g.fix_rel, g.fix_rel_cov, g.fix_xy, g.fix_sigma, strict=True)
        ):
            assert self.vkey is not None  # (__init__)
            out.append(gtsam.BetweenFactorPose2(
                wkey(r), self.vkey(i), gtsam.Pose2(*map(float, rel)),
                gtsam.noiseModel.Gaussian.Covariance(np.asarray(c) * self.inflation),
            ))  # fmt: skip
            base = gtsam.noiseModel.Isotropic.Sigma(2, float(sg) * np.sqrt(self.inflation))
            noise = base if kern is None else gtsam.noiseModel.Robust.Create(kern, base)
            out.append(gtsam.PoseTranslationPrior2D(
                self.vkey(i), gtsam.Point2(float(xy[0]), float(xy[1])), noise
            ))  # fmt: skip
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
        """Every saved factor: :meth:`pose_factors`, the tree priors, then the bearing-range
        factors on ``W(i)`` / ``L(slot)``; ``alias`` maps a landmark slot to the slot its
        factors now point to (merged trees)."""
        from stemmap.slam.gnss import robust_kernel
        from stemmap.slam.relocalise import joint_factor

        g, f = self.saved, np.sqrt(self.inflation)
        to = (lambda r: r) if alias is None else (lambda r: np.asarray(alias, np.int64)[r])
        slots = to(self.slot[g.meas_tree])
        trees: list[Any] = []
        kern = robust_kernel(gtsam, g.tprior_robust, g.tprior_robust_k)
        for j, xy, c in zip(to(self.slot[g.tprior_tree]).tolist(), g.tprior_mean, g.tprior_cov,
                            strict=True):  # fmt: skip
            noise = gtsam.noiseModel.Gaussian.Covariance(np.asarray(c) * self.inflation)
            if kern is not None:
                noise = gtsam.noiseModel.Robust.Create(kern, noise)
            trees.append(gtsam.PriorFactorPoint2(lkey(j), np.asarray(xy, np.float64), noise))
        if g.joint_tree.size:
            trees.append(
                joint_factor(g.joint_sqrt / f, g.joint_mean, to(self.slot[g.joint_tree]), lkey)
            )
        return (
            self.pose_factors(gtsam)
            + trees
            + [
                gtsam.BearingRangeFactor2D(
                    self.wkey(i), lkey(j), gtsam.Rot2(b), r, meas_noise(np.array([sb, sr]) * f)
                )
                for i, j, (b, r, sb, sr) in zip(
                    g.meas_pose.tolist(), slots.tolist(), g.meas.tolist(), strict=True
                )
            ]
        )


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
    map_fac: list[Any] = (),  # type: ignore[assignment]
    prior_robust: tuple[str, float] = ("none", 1.0),
    joint: tuple[FloatArray, FloatArray] | None = None,
    gnss_fac: list[Any] = (),  # type: ignore[assignment]
    gnss_robust: tuple[str, float] = ("none", 1.0),
) -> SavedGraph:
    """The session graph at ``values`` as a :class:`SavedGraph`: the continued earlier graph
    (``cont``: its poses first, then this session's graph keyframes ``gk``), the kept trees
    ``keep`` (tree id = landmark slot, as in trees.csv), the odometry factors ``odo_fac`` and
    pose priors ``pose_priors`` (``BetweenFactorPose2`` / ``PriorFactorPose2`` on ``W`` / ``X``
    keys), and the measurements ``meas_rec`` (keyframe, slot, bearing, range, sigmas) on kept
    trees (after merging: on ``alias[slot]``). Measurements of trees that are not kept (fewer
    than ``min_obs`` observations, not in trees.csv) are dropped with them.

    Format 2: the prior map's per-tree priors ``map_fac`` (``PriorFactorPoint2`` or None per
    prior tree, after merging on the representative; kernel ``prior_robust`` = (name, width))
    or its joint prior ``joint`` = (``U``, (n, 2) means of prior slots 0..n-1); the GNSS
    factors ``gnss_fac`` (``BetweenFactorPose2(X, Z)``, ``PoseTranslationPrior2D(Z)`` per fix,
    kernel ``gnss_robust``); a continued graph's own priors and fixes carried over."""
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
    extra = _export_priors(gtsam, values, tree_row, alias, row_of, LK, cont, map_fac,
                           prior_robust, joint, gnss_fac, gnss_robust)  # fmt: skip
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
        **extra,
    )


def _export_priors(
    gtsam: Any,
    values: Any,
    tree_row: np.ndarray,
    alias: np.ndarray,
    row_of: dict[int, int],
    lkey: Callable[[int], int],
    cont: ContinuedGraph | None,
    map_fac: list[Any],
    prior_robust: tuple[str, float],
    joint: tuple[FloatArray, FloatArray] | None,
    gnss_fac: list[Any],
    gnss_robust: tuple[str, float],
) -> dict[str, Any]:
    """The format-2 arrays of :func:`export_graph` (tree rows ``tree_row[alias[slot]]``)."""
    from stemmap.errors import StemmapError

    out: dict[str, Any] = {}
    tp_i: list[int] = []
    tp_m: list[Any] = []
    tp_c: list[Any] = []
    robust = prior_robust
    fx: dict[str, list[Any]] = {k: [] for k in ("pose", "rel", "rel_cov", "antenna", "xy", "sigma")}
    f_robust = gnss_robust
    if cont is not None:  # the continued graph's own (its trees re-rowed, its poses not)
        g0 = cont.saved
        rows = tree_row[alias[cont.slot[g0.tprior_tree]]]
        tp_i, tp_m, tp_c = rows.tolist(), list(g0.tprior_mean), list(g0.tprior_cov)
        robust = (g0.tprior_robust, g0.tprior_robust_k) if g0.tprior_tree.size else robust
        if g0.joint_tree.size:
            joint_rows = tree_row[alias[cont.slot[g0.joint_tree]]]
            out.update(joint_tree=joint_rows, joint_mean=g0.joint_mean, joint_sqrt=g0.joint_sqrt)
        for i in range(g0.n_fixes):
            assert cont.vkey is not None
            a = values.atPose2(cont.vkey(i))
            fx["antenna"].append((a.x(), a.y(), a.theta()))
        fx["pose"] = g0.fix_pose.tolist()
        fx["rel"], fx["rel_cov"] = list(g0.fix_rel), list(g0.fix_rel_cov)
        fx["xy"], fx["sigma"] = list(g0.fix_xy), list(g0.fix_sigma)
        if g0.n_fixes:
            f_robust = (g0.fix_robust, g0.fix_robust_k)
    for fac in map_fac:
        if fac is None:
            continue
        slot = int(gtsam.Symbol(int(fac.keys()[0])).index())
        tp_i.append(int(tree_row[alias[slot]]))
        tp_m.append(np.asarray(fac.prior(), dtype=np.float64))
        tp_c.append(_gaussian_cov(fac.noiseModel()))
    if joint is not None:
        u, xy = joint
        out.update(joint_tree=tree_row[alias[np.arange(xy.shape[0])]], joint_mean=xy,
                   joint_sqrt=u)  # fmt: skip
    for b_f, p_f in zip(gnss_fac[0::2], gnss_fac[1::2], strict=True):
        kx, kz = (int(k) for k in b_f.keys())  # noqa: SIM118 (a GTSAM factor)
        m, a = b_f.measured(), values.atPose2(kz)
        fx["pose"].append(row_of[kx])
        fx["rel"].append((m.x(), m.y(), m.theta()))
        fx["rel_cov"].append(_gaussian_cov(b_f.noiseModel()))
        fx["antenna"].append((a.x(), a.y(), a.theta()))
        fx["xy"].append(np.asarray(p_f.measured(), dtype=np.float64))
        fx["sigma"].append(float(np.sqrt(_gaussian_cov(p_f.noiseModel())[0, 0])))
    if (np.asarray(tp_i, dtype=np.int64) < 0).any() or (
        "joint_tree" in out and (out["joint_tree"] < 0).any()
    ):
        # (prior trees are always kept: lm_nobs >= min_obs; this would be a bookkeeping bug)
        raise StemmapError("session graph: a prior tree is not in the map; graph not written")
    out.update(
        tprior_tree=np.asarray(tp_i, dtype=np.int64),
        tprior_mean=np.asarray(tp_m, dtype=np.float64).reshape(-1, 2),
        tprior_cov=np.asarray(tp_c, dtype=np.float64).reshape(-1, 2, 2),
        tprior_robust=str(robust[0]), tprior_robust_k=float(robust[1]),
        fix_pose=np.asarray(fx["pose"], dtype=np.int64),
        fix_rel=np.asarray(fx["rel"], dtype=np.float64).reshape(-1, 3),
        fix_rel_cov=np.asarray(fx["rel_cov"], dtype=np.float64).reshape(-1, 3, 3),
        fix_antenna=np.asarray(fx["antenna"], dtype=np.float64).reshape(-1, 3),
        fix_xy=np.asarray(fx["xy"], dtype=np.float64).reshape(-1, 2),
        fix_sigma=np.asarray(fx["sigma"], dtype=np.float64),
        fix_robust=str(f_robust[0]), fix_robust_k=float(f_robust[1]),
    )  # fmt: skip
    return out


def graph_stats(cont: ContinuedGraph | None) -> dict[str, int | float]:
    """Run statistics of the continued graph (empty without one)."""
    if cont is None:
        return {}
    g = cont.saved
    return {
        "continued_poses": g.n_poses,
        "continued_trees": int(g.trees.shape[0]),
        "continued_factors": g.n_factors,
        "continued_gnss_fixes": g.n_fixes,
    }
