"""Revisits in the iSAM2 back-end: a keyframe that adds no information adds no pose (ours).

A drive that revisits a mapped stand again and again (a forwarder's daily work, the soak of
``benchmarks/soak.py``) must not grow the factor graph with every pass: iSAM2's memory and the
work of each update grow with the graph, and the final batch step with it. Following the
*reduced pose graph* of Johannsson, Kaess, Fallon and Leonard (2013, "Temporally scalable
visual SLAM using a reduced pose graph", ICRA: the graph grows with the explored area, not
with time), :class:`stemmap.slam.graph.Isam2Slam` keeps a keyframe out of the graph when it
only re-observes well-mapped trees:

* **redundant keyframe** (:func:`redundant`): every tree that would get a factor from the
  keyframe's window is already in the graph with at least ``revisit_factors`` measurement
  factors (so one more factor moves it by at most ~1/``revisit_factors`` of its own scatter),
  and the keyframe carries no GNSS fix. A keyframe without any tree factor (a transit) is
  redundant too: its pose only chains odometry, which the composed factor below carries
  exactly. The front-end still tracks and associates every scan against the map (so
  revisits still find their trees), the keyframe's measurements are kept aside;
* the next keyframe that does enter the graph is linked to the previous one in the graph by
  the **composed odometry** of the keyframes between (:func:`compose_increments`: the
  increments composed in SE(2), the covariance carried with the adjoint, as GTSAM's
  ``Pose2.compose`` Jacobians do), so no odometry information is lost;
* after the final batch step, the poses of the left-out keyframes are **localised** against
  the final map (:func:`localise_skipped`): per run of consecutive left-out keyframes, one
  small Levenberg-Marquardt problem with their odometry chain between the two graph
  keyframes around them (held at their final estimates), their own bearing-range
  measurements, and the trees as priors at their final estimates with their marginal
  covariances (the mechanism of :mod:`stemmap.slam.relocalise` for prior maps). Its size is
  the run's, so the cost of the whole step is linear in the drive and its memory bounded by
  the longest run.

Two additions make it hold on long drives (third session; docs/algorithms/slam.md
"Localisation mode"): between iSAM2 updates the tracker is **localised on the map**
(:mod:`stemmap.slam._graph_localise`; a fit the map contradicts puts the next keyframes into
the graph), and the graph is **bounded by area**: where a place already holds
``revisit_keyframes`` graph keyframes of an earlier visit within ``revisit_radius``
(:class:`PlaceCounter`: added ``revisit_after_m`` or more of driving before; a stop or slow
driving is one visit), a keyframe whose trees are all in the graph stays out even if some
have fewer than ``revisit_factors`` factors. A fourth session bounded it **by tree** too
(:class:`TreeVisits`): a tree that got factors on ``revisit_settle_visits`` earlier visits
no longer pulls keyframes in (trunks at the edge of range gained a few factors on every pass
and kept the 10x soak's graph growing; off by default: it cost one start time of the single
Victoria Park drive its path). The mode is on by
default (``revisit_factors = 15``); measured on the Victoria Park log replayed 10x as
revisits in docs/reliability.md "Soak".

What this is meant to bound: the graph, iSAM2's memory and per-update work, the final batch and
marginals grow with the mapped area (and with trees still below ``revisit_factors``), not
with drive time. Per-frame bookkeeping (trajectory, dead reckoning, drift variances: ~230
bytes per scan) stays linear in the drive, as for every back-end; the left-out keyframes'
measurements (:class:`~stemmap.slam._graph_leftout.LeftOutMeasurements`, 40 bytes each) are
held in memory up to a bound and spilled to a temporary file beyond it. On the 10x soak
the graph still gains 25-60 keyframes per late pass (young and new trees); a seventh session
anchors a keyframe that enters after a long left-out run by a prior at its tracked pose
(:func:`anchor_prior`) instead of a long odometry edge, which halved iSAM2's memory growth per
pass (docs/reliability.md "iSAM2: long left-out runs anchored"). An eighth counts *visits* of
a place by every keyframe, in or out of the graph (:class:`PlaceVisits`,
``revisit_place_visits = 3``): a place whose revisits were all left out still fills, so
trunks at the edge of range stop pulling keyframes in after three visits; the 10x soak's
growth fell from 6.37 to 2.0 MB per pass, the late passes add 6-14 keyframes (new trees, a
lost tracker). :class:`RevisitGate` holds every decision, and keeps a keyframe that closes
a loop whatever the bounds say (docs/algorithms/slam.md "The place bound counts every
visit"). A tenth session made most lost-tracker events go away (false alarms of the map fit,
:mod:`stemmap.slam._graph_localise`) and added, as an option (``revisit_hold_new``), new
trees on well-visited ground held out of the graph and mapped at the end from the left-out
keyframes' poses (:func:`map_held`): 1-5 graph keyframes per late pass instead of 4-18, but
1-1.6 % of path on the single drive at some start times (docs/reliability.md "Soak").
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from stemmap.slam._graph_leftout import LeftOutMeasurements
from stemmap.slam.motion import between, compose
from stemmap.types import FloatArray

__all__ = [
    "LeftOutMeasurements",
    "PlaceCounter",
    "PlaceVisits",
    "RevisitGate",
    "TreeVisits",
    "anchor_prior",
    "compose_increments",
    "held_into_map",
    "localise_skipped",
    "map_held",
    "redundant",
]


def _adjoint_inv(d: FloatArray) -> FloatArray:
    """GTSAM's ``Pose2.AdjointMap`` of ``d⁻¹`` for ``d = (x, y, θ)``: [[R, (y', -x')], [0, 1]];
    ``d`` (3,) -> (3, 3) or (n, 3) -> (n, 3, 3)."""
    d = np.asarray(d, dtype=np.float64)
    c, s = np.cos(d[..., 2]), np.sin(d[..., 2])
    xi, yi = -c * d[..., 0] - s * d[..., 1], s * d[..., 0] - c * d[..., 1]  # translation of d⁻¹
    z, o = np.zeros_like(c), np.ones_like(c)
    rows = (np.stack((c, s, yi), -1), np.stack((-s, c, -xi), -1), np.stack((z, z, o), -1))
    return np.stack(rows, -2)


def compose_increments(d: FloatArray, cov: FloatArray) -> tuple[FloatArray, FloatArray]:
    """One SE(2) increment and its covariance from consecutive increments ``d`` (m, 3), ``cov``.

    ``D = d_0 ∘ d_1 ∘ ... ∘ d_m-1``; covariances in GTSAM's convention (right perturbation,
    tangent order x, y, θ): ``C ← Ad(d_i⁻¹) C Ad(d_i⁻¹)ᵀ + cov_i``, the first-order
    propagation of ``Pose2.compose`` (Barfoot 2017, State Estimation for Robotics, eq. 7.300
    for SE(3); the SE(2) adjoint here). Exact for the mean; the covariance is first order.
    """
    D = np.array(d[0], dtype=np.float64)
    C = np.array(cov[0], dtype=np.float64)
    for i in range(1, d.shape[0]):
        A = _adjoint_inv(d[i])
        C = A @ C @ A.T + cov[i]
        c, s = np.cos(D[2]), np.sin(D[2])
        D = np.array(
            (D[0] + c * d[i, 0] - s * d[i, 1], D[1] + s * d[i, 0] + c * d[i, 1], D[2] + d[i, 2])
        )
    D[2] = (D[2] + np.pi) % (2.0 * np.pi) - np.pi
    return D, 0.5 * (C + C.T)


def anchor_prior(
    gtsam: Any, key: int, pose: FloatArray, steps: FloatArray, step_cov: FloatArray
) -> Any:
    """Prior on a keyframe that enters the graph after a long run of left-out keyframes.

    Instead of the composed odometry factor from the last graph keyframe (``steps`` /
    ``step_cov``: the increments of the run, :func:`compose_increments`), the keyframe gets a
    ``PriorFactorPose2`` at ``pose``, its tracked pose (the front-end's, localised on the map
    during the run), with the covariance of the composed odometry. The factor keeps the
    keyframe well-posed, is as weak as the odometry it replaces, and -- the reason for it --
    ties no remote part of the graph together: on the 10x Victoria Park soak the late
    passes' long odometry edges (one per keyframe a young or new tree pulled in, between
    graph keyframes hundreds of metres of driving apart) made iSAM2's Bayes tree grow by
    ~12 MB per pass; docs/reliability.md "iSAM2: long left-out runs anchored". What is
    dropped: the relative constraint from a pose many metres of odometry back, whose
    covariance has grown with the run (ours; the reduced pose graph of Johannsson et al. 2013
    keeps every such edge).
    """
    _, cov = compose_increments(steps, step_cov)
    return gtsam.PriorFactorPose2(
        key,
        gtsam.Pose2(float(pose[0]), float(pose[1]), float(pose[2])),
        gtsam.noiseModel.Gaussian.Covariance(cov),
    )


def redundant(
    trees: np.ndarray,
    in_graph: np.ndarray,
    n_factors: np.ndarray,
    min_f: int,
    settled: np.ndarray | None = None,
) -> bool:
    """True when a keyframe whose window measures ``trees`` adds nothing the graph needs.

    Every tree is in the graph with at least ``min_f`` measurement factors, or is ``settled``
    (a bool per tree: no longer allowed to pull keyframes in: at a place the graph already
    covers, :class:`PlaceCounter`, or on a later visit of the tree, :class:`TreeVisits`)
    -- vacuously true with no tree; ``min_f <= 0`` disables the rule (every keyframe enters
    the graph).
    """
    if min_f <= 0:
        return False
    if trees.size == 0:
        return True
    enough = n_factors[trees] >= min_f
    if settled is not None:
        enough |= settled[trees]
    return bool(np.all(in_graph[trees]) and np.all(enough))


class PlaceCounter:
    """Graph keyframes per place: how many lie within ``radius`` (m) of a point, counting only
    those of an earlier *visit* (a hash grid of ``radius``-sized cells; exact disc counts).
    Bounds the graph by area (``Isam2Config.revisit_keyframes``).

    A keyframe is stored with its path distance ``s`` (m driven since the start); one counts
    towards the place of a later keyframe at ``s'`` only when ``s' - s >= after_m``: the
    vehicle drove that far in between, so it left the place and came back. A vehicle that
    drives slowly or stands still stays in one visit however long it takes (time would call
    a stop a revisit)."""

    def __init__(self, radius: float, per_place: int = 1, after_m: float = 0.0) -> None:
        self.radius = float(radius)
        self.per_place = int(per_place)
        self.after_m = float(after_m)
        self._cells: dict[tuple[int, int], list[tuple[float, float, float]]] = {}

    def _cell(self, x: float, y: float) -> tuple[int, int]:
        return int(np.floor(x / self.radius)), int(np.floor(y / self.radius))

    def add(self, xy: FloatArray, s: float = 0.0) -> None:
        """A graph keyframe at ``xy`` (2,) (m), at path distance ``s`` (m)."""
        x, y = float(xy[0]), float(xy[1])
        self._cells.setdefault(self._cell(x, y), []).append((x, y, s))

    def full(self, xy: FloatArray, s: float) -> bool:
        """At path distance ``s`` (m), ``xy`` holds ``per_place`` keyframes of an earlier visit
        (added at path distance ``s - after_m`` or less)."""
        return self.count(xy, s - self.after_m) >= self.per_place

    def count(self, xy: FloatArray, upto: float = np.inf) -> int:
        """Graph keyframes within ``radius`` of ``xy`` (2,) added at path distance <= ``upto``."""
        x, y = float(xy[0]), float(xy[1])
        cx, cy = self._cell(x, y)
        r2 = self.radius * self.radius
        n = 0
        for i in (cx - 1, cx, cx + 1):
            for j in (cy - 1, cy, cy + 1):
                for px, py, ps in self._cells.get((i, j), ()):
                    if ps <= upto and (px - x) ** 2 + (py - y) ** 2 <= r2:
                        n += 1
        return n


class TreeVisits:
    """Visits of every tree, by path distance, and in how many of them it got graph factors.

    Bounds the graph on revisits by tree (``Isam2Config.revisit_settle_visits``): a tree that
    got measurement factors on ``settle`` earlier visits pulls no keyframe into the graph on a
    later visit, whatever its factor count (a trunk at the edge of range, seen in a few
    keyframes of every pass, otherwise pulls keyframes in on every pass: the 10x Victoria Park
    soak's graph kept growing with them, docs/reliability.md "iSAM2 memory per pass"). A new
    visit of a tree starts when it is measured ``after_m`` m of driving (or more) after its
    last measurement (as :class:`PlaceCounter`: a stop is still one visit). Its measurements
    on later visits still serve the tracker and the final localisation of the left-out
    keyframes (the left-out store), only not the graph. ``settle = 0``: off.
    """

    def __init__(self, after_m: float, settle: int, capacity: int = 1024) -> None:
        self.after_m = float(after_m)
        self.settle = int(settle)
        self._seen_s = np.full(capacity, -np.inf)  # path distance of the last measurement
        self._visit = np.zeros(capacity, dtype=np.int64)  # current visit (1 = first)
        self._fac_visits = np.zeros(capacity, dtype=np.int64)  # visits with a graph factor
        self._fac_last = np.zeros(capacity, dtype=np.int64)  # visit of the last graph factor

    def _room(self, n: int) -> None:
        cap = self._seen_s.shape[0]
        if n <= cap:
            return
        g = max(n, 2 * cap) - cap
        self._seen_s = np.concatenate((self._seen_s, np.full(g, -np.inf)))
        for name in ("_visit", "_fac_visits", "_fac_last"):
            setattr(self, name, np.concatenate((getattr(self, name), np.zeros(g, np.int64))))

    def see(self, trees: np.ndarray, s: float) -> None:
        """``trees`` measured at path distance ``s`` (m; non-decreasing between calls)."""
        if trees.size == 0:
            return
        self._room(int(trees.max()) + 1)
        new = s - self._seen_s[trees] >= self.after_m  # also the first measurement (-inf)
        self._visit[trees] += new
        self._seen_s[trees] = s

    def factored(self, trees: np.ndarray) -> None:
        """``trees`` (seen, :meth:`see`) got a measurement factor in the graph."""
        if trees.size == 0:
            return
        self._fac_visits[trees] += self._fac_last[trees] != self._visit[trees]
        self._fac_last[trees] = self._visit[trees]

    def settled(self, n: int) -> np.ndarray | None:
        """Bool per tree ``0..n-1``: graph factors on ``settle`` visits before its current one
        (None when off)."""
        if self.settle <= 0:
            return None
        self._room(n)
        done = self._fac_visits[:n] - (self._fac_last[:n] == self._visit[:n])
        return done >= self.settle


class PlaceVisits:
    """Visits of every place by keyframes in or out of the graph: how many times the vehicle
    came within ``radius`` (m) of a point, visits told apart by ``after_m`` m of driving.

    The area bound by visits (``Isam2Config.revisit_place_visits``): unlike
    :class:`PlaceCounter` (graph keyframes only), a left-out keyframe counts too, so a place
    whose revisits were all left out still fills up. A keyframe is stored with its path
    distance ``s`` (m driven since the start); the stored distances within ``radius`` of a
    point, sorted, split into visits wherever two are ``after_m`` or more apart (one visit
    spans a few metres of path: a 2 m disc on a straight road, a stop, a slow turn). Storage is
    bounded by area: a keyframe is not stored where the place already holds ``cap`` visits
    (counting them again cannot change a decision).
    """

    def __init__(self, radius: float, after_m: float, cap: int) -> None:
        self.radius = float(radius)
        self.after_m = float(after_m)
        self.cap = int(cap)
        self._cells: dict[tuple[int, int], list[tuple[float, float, float]]] = {}

    def _near(self, x: float, y: float) -> list[float]:
        cx, cy = int(np.floor(x / self.radius)), int(np.floor(y / self.radius))
        r2 = self.radius * self.radius
        out = []
        for i in (cx - 1, cx, cx + 1):
            for j in (cy - 1, cy, cy + 1):
                for px, py, ps in self._cells.get((i, j), ()):
                    if (px - x) ** 2 + (py - y) ** 2 <= r2:
                        out.append(ps)
        return out

    def count(self, xy: FloatArray, upto: float = np.inf) -> int:
        """Visits within ``radius`` of ``xy`` (2,) by keyframes at path distance <= ``upto``."""
        s = np.sort([q for q in self._near(float(xy[0]), float(xy[1])) if q <= upto])
        if s.size == 0:
            return 0
        return 1 + int(np.count_nonzero(np.diff(s) >= self.after_m))

    def add(self, xy: FloatArray, s: float) -> None:
        """A keyframe (in or out of the graph) at ``xy`` (2,), path distance ``s`` (m)."""
        x, y = float(xy[0]), float(xy[1])
        if self.count(xy) >= self.cap:
            return
        key = int(np.floor(x / self.radius)), int(np.floor(y / self.radius))
        self._cells.setdefault(key, []).append((x, y, float(s)))

    def visited(self, xy: FloatArray, s: float, n: int) -> bool:
        """At path distance ``s``, ``xy`` had ``n`` or more earlier visits (ended ``after_m``
        or more of driving before ``s``)."""
        return n > 0 and self.count(xy, s - self.after_m) >= n


class RevisitGate:
    """Which keyframe stays out of the graph on revisits: the area, visit and tree bounds of
    the localisation mode, and the loop closures they must not drop, in one place
    (:class:`stemmap.slam.graph.Isam2Slam` asks it once per keyframe, :meth:`leave_out`, and
    tells it which keyframes and factors entered).

    A keyframe stays out when :func:`redundant` says so, with a young tree (fewer than
    ``revisit_factors`` factors) counted as settled where the place is *full*: it holds
    ``revisit_keyframes`` graph keyframes of an earlier visit (:class:`PlaceCounter`), or was
    driven past ``revisit_place_visits`` times before by keyframes in or out of the graph
    (:class:`PlaceVisits`), or the tree is settled by visits (:class:`TreeVisits`). Whatever
    those say, a **loop closure** enters (``revisit_keep_loops``): the keyframe would be
    linked to the graph by odometry (``linked``: not anchored, :func:`anchor_prior`), the
    graph keyframes since the chain was last tied to the map span ``revisit_after_m`` m of
    driving or more, and it measures a tree whose last graph factor lies ``revisit_after_m``
    m or more of driving back. That measurement is the constraint that pulls the drift of
    the chain (and of the trees it mapped) back onto the map; a graph keyframe *ties* the
    chain when it measures such a tree or is anchored. The bounds above count visits and
    factors, not whether the chain needs it. In localisation mode the graph keyframes are
    sparse and each one measures the map's trees (it ties itself), so the rule stays quiet
    there; it fires where the vehicle maps new ground and comes back.

    With ``revisit_hold_new = N``, a tree first measured (in a keyframe that may stay out)
    where the place had N or more earlier visits is *held*: it counts as in the graph there
    (pulls no keyframe in) until a graph keyframe measures it (:meth:`factored`); the
    back-end maps the held trees at the end (:func:`held_into_map`).

    ``config`` is the back-end's :class:`~stemmap.slam._graph_config.Isam2Config`; ``xy0`` the
    first keyframe's position (always in the graph).
    """

    def __init__(self, config: Any, xy0: FloatArray, capacity: int = 1024) -> None:
        c = config
        self.min_f = int(c.revisit_factors)
        self.after_m = float(c.revisit_after_m)
        self.places = PlaceCounter(c.revisit_radius, c.revisit_keyframes, c.revisit_after_m)
        self.places.add(xy0, 0.0)
        self.n_visits = int(c.revisit_place_visits)
        self.visits = PlaceVisits(c.revisit_radius, c.revisit_after_m, self.n_visits + 1)
        self.visits.add(xy0, 0.0)
        self.trees = TreeVisits(c.revisit_after_m, c.revisit_settle_visits)
        self.keep_loops = bool(c.revisit_keep_loops)
        self.hold = int(c.revisit_hold_new)
        # (PlaceVisits stores up to cap visits per place: enough for either bound)
        self.visits.cap = max(self.visits.cap, self.hold + 1)
        self._held = np.zeros(capacity, dtype=bool)  # new trees held out of the graph
        self.n_held = 0  # trees ever held
        self._fac_s = np.full(capacity, np.inf)  # path distance of each tree's last factor
        self._s_tie = 0.0  # the graph chain was last tied to the map here (m)
        self._s_graph = 0.0  # the last graph keyframe (m)
        self.n_loops = 0  # keyframes kept as loop closures (only)

    def _stale(self, trees: np.ndarray, s: float) -> bool:
        """One of ``trees`` got its last graph factor ``after_m`` or more of driving before
        ``s`` (trees without a factor are not stale)."""
        if trees.size == 0:
            return False
        n = int(trees.max()) + 1
        if n > self._fac_s.shape[0]:
            g = max(n, 2 * self._fac_s.shape[0]) - self._fac_s.shape[0]
            self._fac_s = np.concatenate((self._fac_s, np.full(g, np.inf)))
        return bool(np.any(s - self._fac_s[trees] >= self.after_m))

    def leave_out(
        self,
        xy: FloatArray,
        s: float,
        trees: np.ndarray,
        in_graph: np.ndarray,
        n_factors: np.ndarray,
        allowed: bool = True,
        linked: bool = True,
    ) -> bool:
        """True when the keyframe at ``xy`` (its front-end position), path distance ``s`` (m),
        measuring ``trees`` stays out of the graph; ``allowed = False`` (the first keyframes,
        a GNSS fix, a lost tracker) records the keyframe and keeps it in; ``linked``: it
        would enter with an odometry factor to the last graph keyframe (not anchored)."""
        full = self.places.full(xy, s) or self.visits.visited(xy, s, self.n_visits)
        hold = self.hold > 0 and self.visits.visited(xy, s, self.hold)
        self.visits.add(xy, s)
        self.trees.see(trees, s)
        if not allowed:
            return False
        if hold and trees.size:
            # new trees on full ground wait outside the graph (held, see the class doc)
            n = in_graph.shape[0]
            if n > self._held.shape[0]:
                self._held = np.concatenate((self._held, np.zeros(n - self._held.shape[0], bool)))
            new = trees[~in_graph[trees] & ~self._held[trees]]
            self._held[new] = True
            self.n_held += int(new.size)
            in_graph = in_graph | self._held[:n]
        settled = in_graph if full else self.trees.settled(in_graph.shape[0])
        if not redundant(trees, in_graph, n_factors, self.min_f, settled):
            return False
        if (
            self.keep_loops
            and linked
            and self._s_graph - self._s_tie >= self.after_m
            and self._stale(trees[in_graph[trees]], s)
        ):
            self.n_loops += 1
            return False
        return True

    def entered(self, xy: FloatArray, s: float, anchored: bool = False) -> None:
        """A keyframe at ``xy``, path distance ``s``, entered the graph (after the first);
        ``anchored``: by a prior at its tracked pose (:func:`anchor_prior`), which ties it."""
        self.places.add(xy, s)
        self._s_graph = s
        if anchored:
            self._s_tie = s

    def factored(self, trees: np.ndarray, s: float = 0.0) -> None:
        """``trees`` got one measurement factor each in the graph, from a keyframe at path
        distance ``s``."""
        self.trees.factored(trees)
        if self.hold:  # a held tree measured from a graph keyframe is in the graph now
            self._held[trees[trees < self._held.shape[0]]] = False
        if self._stale(trees, s):
            self._s_tie = s  # a stale tree measured from the chain: tied to the map
        self._fac_s[trees] = s

    def held(self, n: int) -> np.ndarray:
        """Bool per tree ``0..n-1``: held out of the graph (never measured from a graph
        keyframe since it was first seen on full ground)."""
        out = np.zeros(n, dtype=bool)
        m = min(n, self._held.shape[0])
        out[:m] = self._held[:m]
        return out

    def tree_visits(self, n: int) -> np.ndarray:
        """Visits (by path distance, :class:`TreeVisits`) of every tree ``0..n-1`` so far."""
        self.trees._room(n)
        return self.trees._visit[:n].copy()


def map_held(
    skipped: Mapping[int, tuple[np.ndarray, FloatArray, FloatArray, FloatArray]]
    | LeftOutMeasurements,
    kf_pose: FloatArray,
    held: np.ndarray,
    floor: Sequence[float],
    gate_chi2: float = 13.8,
) -> tuple[FloatArray, FloatArray, np.ndarray]:
    """Positions of the held trees from the left-out keyframes' final poses (their only
    measurements): per tree the information-weighted mean of its measurements projected from
    ``kf_pose`` (nk, 3; sensor poses after :func:`localise_skipped`), each with the
    bearing-range covariance (as :func:`stemmap.slam._graph_localise._points`) plus the pose
    uncertainty ``floor`` = (σ_x, σ_y, σ_θ) (m, m, rad; the tracker's floor: the keyframes
    are localised on the map), one re-weighting with measurements beyond ``gate_chi2``
    dropped. The covariance is the mean's plus the position floor (the poses' errors are
    shared between the measurements, they do not average out). Triangulation with known
    poses (Thrun, Burgard and Fox 2005, Probabilistic Robotics, sec. 10.2, the landmark
    initialisation of EKF SLAM, as a least-squares mean).

    Returns ``(xy (n, 2), cov (n, 2, 2), n_meas (n,))`` for the trees ``held`` (bool per
    tree, n = ``held.sum()``, in tree order); NaN for a tree never measured.
    """
    idx = np.flatnonzero(held)
    pos = np.full(held.shape[0], -1, dtype=np.int64)
    pos[idx] = np.arange(idx.size)
    pts: list[FloatArray] = []
    infos: list[FloatArray] = []
    owner: list[np.ndarray] = []
    sxy2 = float(floor[0]) ** 2 + float(floor[1]) ** 2
    for k in skipped:
        trees, brg, rng, sig = skipped[k]
        sel = trees < held.shape[0]
        sel[sel] = held[trees[sel]]
        if not np.any(sel):
            continue
        x, y, th = kf_pose[k]
        ang = th + brg[sel]
        r = rng[sel]
        ca, sa = np.cos(ang), np.sin(ang)
        pts.append(np.column_stack((x + r * ca, y + r * sa)))
        vr = sig[sel, 1] ** 2 + 0.5 * sxy2
        vt = (r * sig[sel, 0]) ** 2 + (r * float(floor[2])) ** 2 + 0.5 * sxy2
        cov = np.empty((r.size, 2, 2))
        cov[:, 0, 0] = ca * ca * vr + sa * sa * vt
        cov[:, 1, 1] = sa * sa * vr + ca * ca * vt
        cov[:, 0, 1] = cov[:, 1, 0] = ca * sa * (vr - vt)
        infos.append(np.linalg.inv(cov))
        owner.append(pos[trees[sel]])
    xy = np.full((idx.size, 2), np.nan)
    out_cov = np.full((idx.size, 2, 2), np.nan)
    n_meas = np.zeros(idx.size, dtype=np.int64)
    if not pts:
        return xy, out_cov, n_meas
    p, w, o = np.concatenate(pts), np.concatenate(infos), np.concatenate(owner)
    use = np.ones(o.size, dtype=bool)
    for it in range(2):
        lam = np.zeros((idx.size, 2, 2))
        eta = np.zeros((idx.size, 2))
        np.add.at(lam, o[use], w[use])
        np.add.at(eta, o[use], np.einsum("mij,mj->mi", w[use], p[use]))
        ok = np.linalg.det(lam) > 0
        xy[ok] = np.linalg.solve(lam[ok], eta[ok][:, :, None])[:, :, 0]
        if it == 0:  # drop the measurements the others contradict
            e = p - xy[o]
            use = np.einsum("mi,mij,mj->m", e, w, e) <= gate_chi2
    n_meas = np.bincount(o[use], minlength=idx.size)
    ok = n_meas > 0
    xy[~ok] = np.nan
    out_cov[ok] = np.linalg.inv(lam[ok]) + 0.5 * sxy2 * np.eye(2)
    return xy, out_cov, n_meas


def held_into_map(
    skipped: Any,
    kf_pose: FloatArray,
    held: np.ndarray,
    visits: np.ndarray,
    lm: tuple[np.ndarray, np.ndarray, np.ndarray],
    cfg: Any,
    keep: np.ndarray,
    pts: FloatArray,
    covs: FloatArray,
    info_j: FloatArray | None,
) -> tuple[np.ndarray, FloatArray | None]:
    """The held trees that are confirmed -- measured on ``cfg.revisit_hold_confirm`` visits and
    in ``cfg.min_obs`` scans -- mapped by :func:`map_held` into ``pts`` / ``covs`` (in place);
    returns ``keep`` with them appended and the trees' joint information extended block-
    diagonally (they are independent of the graph's trees in this estimate). ``lm`` = (dsum,
    dn, nobs) landmark bookkeeping. A held tree that is a duplicate of a mapped tree (the
    batch step's merge rule, :func:`~stemmap.slam._graph_marginals._merge_duplicates`, over
    the mapped and the held trees: a group with a graph tree keeps only that one, a group of
    held trees its most-observed) is dropped, as the batch step merges the graph's own."""
    from stemmap.slam._graph_marginals import _merge_duplicates

    dsum, dn, nobs = lm
    xy, cov, _ = map_held(skipped, kf_pose, held, cfg.track_floor_sigmas)
    idx = np.flatnonzero(held)
    ok = (visits[idx] >= cfg.revisit_hold_confirm) & (nobs[idx] >= cfg.min_obs)
    ok &= np.isfinite(xy).all(axis=1)
    if cfg.merge_dist > 0 and ok.any():
        both = np.concatenate((keep, idx[ok]))
        xy_b = np.concatenate((pts[keep], xy[ok]))
        diam = dsum[both] / np.maximum(dn[both], 1)
        nob = nobs[both] + np.where(np.arange(both.size) < keep.size, 10**9, 0)  # graph first
        sd = cfg.sigma_diameter or math.inf
        rep = _merge_duplicates(xy_b, diam, nob, cfg.merge_dist, 3.0 * sd * math.sqrt(2.0))
        ok[np.flatnonzero(ok)] = rep[keep.size :] == np.arange(keep.size, both.size)
    pts[idx[ok]], covs[idx[ok]] = xy[ok], cov[ok]
    if info_j is not None and ok.any():
        import scipy.linalg

        info_j = scipy.linalg.block_diag(info_j, *np.linalg.inv(cov[ok]))
    return np.concatenate((keep, idx[ok])), info_j


def localise_skipped(
    gtsam: Any,
    skipped: Mapping[int, tuple[np.ndarray, FloatArray, FloatArray, FloatArray]]
    | LeftOutMeasurements,
    kf_pose: FloatArray,
    init: FloatArray,
    steps: FloatArray,
    step_cov: FloatArray,
    tree_xy: FloatArray,
    tree_cov: FloatArray,
    meas_noise: Callable[[FloatArray], Any],
    keys: tuple[Callable[[int], int], Callable[[int], int]],
    anchor_sigmas: Sequence[float] = (1e-3, 1e-3, 1e-4),
    iterations: int = 10,
    held: np.ndarray | None = None,
) -> int:
    """Fill ``kf_pose`` (in place) at the left-out keyframes: each run localised on the map.

    ``skipped`` maps a left-out keyframe to its window's measurements ``(trees, bearing, range,
    sigmas (m, 2))`` (trees already mapped to their merged representatives); ``kf_pose``
    (nk, 3) holds the final sensor poses of the graph keyframes (rows of left-out ones are
    overwritten); ``init`` (nk, 3) the front-end's poses (initial values); ``steps`` /
    ``step_cov`` the odometry increments of keyframe ``k`` to ``k + 1`` and their covariances;
    ``tree_xy`` / ``tree_cov`` the trees' final estimates and marginal covariances (NaN:
    0.1 m). Keyframe 0 is always in the graph. ``held`` (bool per tree): trees without a
    graph estimate (:class:`RevisitGate`'s held trees), whose measurements are not used.
    Returns the number of LM problems solved.
    """
    XK, LK = keys
    nk = kf_pose.shape[0]
    todo = np.array(sorted(skipped), dtype=np.int64)
    if todo.size == 0:
        return 0
    # runs of consecutive left-out keyframes
    breaks = np.flatnonzero(np.diff(todo) > 1) + 1
    anchor = gtsam.noiseModel.Diagonal.Sigmas(np.asarray(anchor_sigmas, dtype=np.float64))
    lm_params = gtsam.LevenbergMarquardtParams()
    lm_params.setMaxIterations(iterations)
    n_solved = 0
    for run in np.split(todo, breaks):
        s, e = int(run[0]), int(run[-1])
        g = gtsam.NonlinearFactorGraph()
        v = gtsam.Values()
        lo, hi = s - 1, e + 1 if e + 1 < nk else e
        for k in (lo, hi):
            if k not in skipped:
                p = gtsam.Pose2(*(float(q) for q in kf_pose[k]))
                g.add(gtsam.PriorFactorPose2(XK(k), p, anchor))
                v.insert(XK(k), p)
        # initial values: the front-end's poses, moved rigidly onto the left anchor's estimate
        start = compose(kf_pose[lo][None], between(init[lo][None], init[s : e + 1]))
        for k in range(s, e + 1):
            v.insert(XK(k), gtsam.Pose2(*(float(q) for q in start[k - s])))
        for k in range(lo, hi):
            dk = steps[k]
            g.add(
                gtsam.BetweenFactorPose2(
                    XK(k),
                    XK(k + 1),
                    gtsam.Pose2(float(dk[0]), float(dk[1]), float(dk[2])),
                    gtsam.noiseModel.Gaussian.Covariance(step_cov[k]),
                )
            )
        seen: set[int] = set()
        for k in range(s, e + 1):
            trees, brg, rng, sig = skipped[k]
            for t, j in enumerate(trees.tolist()):
                if held is not None and j < held.shape[0] and held[j]:
                    continue
                g.add(
                    gtsam.BearingRangeFactor2D(
                        XK(k), LK(j), gtsam.Rot2(float(brg[t])), float(rng[t]), meas_noise(sig[t])
                    )
                )
                if j not in seen:
                    seen.add(j)
                    cj = tree_cov[j]
                    if not np.all(np.isfinite(cj)):
                        cj = np.diag([0.1**2, 0.1**2])
                    xy = tree_xy[j]
                    g.add(
                        gtsam.PriorFactorPoint2(
                            LK(j), np.array(xy, dtype=np.float64),
                            gtsam.noiseModel.Gaussian.Covariance(np.asarray(cj, np.float64)),
                        )
                    )  # fmt: skip
                    v.insert(LK(j), np.array(xy, dtype=np.float64))
        res = gtsam.LevenbergMarquardtOptimizer(g, v, lm_params).optimize()
        for k in range(s, e + 1):
            p = res.atPose2(XK(k))
            kf_pose[k] = (p.x(), p.y(), p.theta())
        n_solved += 1
    return n_solved
