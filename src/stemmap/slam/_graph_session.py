"""An earlier session in the iSAM2 graph: its map's trees as this session's first landmarks.

Split out of ``Isam2Slam._run`` (:mod:`stemmap.slam.graph`; docs/algorithms/slam.md "Maps
reused across sessions"). With ``problem.prior_map`` (relocalised into: the problem's initial
pose is in its frame) the earlier trees become landmarks ``L(0..n-1)`` held by their marginal
covariance as a prior -- per tree (:func:`~stemmap.slam.relocalise.prior_tree_factors`,
robust when ``prior_map_robust`` names a kernel) or by one joint prior over all of them
(:func:`~stemmap.slam.relocalise.joint_prior_factor`, the map's ``information``); with
``problem.prior_graph`` the earlier session's whole graph is continued instead (its poses
``W(i)``, its trees these landmarks, its factors instead of the marginal priors:
:class:`~stemmap.slam._graph_continue.ContinuedGraph`). Either way this session updates the
earlier trees and adds new ones: one merged map.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from stemmap.slam._graph_continue import ContinuedGraph
from stemmap.slam.base import SlamProblem
from stemmap.slam.relocalise import inflate_prior, joint_prior_factor, prior_tree_factors
from stemmap.types import StemMap

__all__ = ["EarlierSession", "seed_earlier_session"]


@dataclass
class EarlierSession:
    """What :func:`seed_earlier_session` put in the graph (kept when the graph is rebuilt).

    ``n_lm``: landmark slots taken by the earlier trees (0 without a prior map); ``pmap``: the
    prior map as this session holds it (covariances x ``prior_map_inflation``); ``cont``: the
    continued graph; ``map_fac``: each earlier tree's prior (None where the continued graph
    holds it); ``joint_fac``: the one joint prior over them, or None.
    """

    n_lm: int = 0
    pmap: StemMap | None = None
    cont: ContinuedGraph | None = None
    map_fac: list[Any] = field(default_factory=list)
    joint_fac: Any = None


def seed_earlier_session(
    gtsam: Any,
    problem: SlamProblem,
    cfg: Any,
    keys: tuple[Callable[[int], int], Callable[[int], int], Callable[[int], int]],
    lm: tuple[Any, Any, Any, Any, Any],
    *,
    meas_noise: Callable[[Any], Any],
    prior_kernel: Any,
    add_factor: Callable[[Any], None],
    add_value: Callable[[int, Any], None],
) -> EarlierSession:
    """Seed the graph with the earlier session of ``problem`` (see the module docs).

    ``keys`` = (L, W, V) symbol makers; ``lm`` = (xy, dsum, dn, nobs, in_graph) landmark arrays
    of the back-end, filled for the earlier trees; ``add_factor`` / ``add_value`` put a factor
    or an initial value in the graph (in this order: the continued graph's values and factors,
    then per tree its value and prior, then the joint prior).
    """
    LK, WK, VK = keys
    lm_xy, lm_dsum, lm_dn, lm_nobs, lm_in_graph = lm
    out = EarlierSession()
    n_prior = 0 if problem.prior_map is None else len(problem.prior_map)
    out.pmap = pmap = (
        None
        if problem.prior_map is None
        else inflate_prior(problem.prior_map, cfg.prior_map_inflation)
    )
    if pmap is not None and problem.prior_graph is not None:
        out.cont = cont = ContinuedGraph(
            problem.prior_graph, pmap, WK, cfg.prior_graph_inflation, vkey=VK
        )
        for key_w, val_w in cont.values(gtsam):
            add_value(key_w, val_w)
        for fac_w in cont.factors(gtsam, LK, meas_noise):
            add_factor(fac_w)
    if pmap is not None and len(pmap):
        out.n_lm = n_prior
        cont_xy = None if out.cont is None else out.cont.tree_xy(n_prior)
        for j_p, (xy_p, d_p, n_p, fac_p) in enumerate(
            prior_tree_factors(pmap, LK, cfg.min_obs, kernel=prior_kernel)
        ):
            lm_xy[j_p] = xy_p
            if math.isfinite(d_p):
                lm_dsum[j_p], lm_dn[j_p] = d_p * n_p, n_p
            lm_nobs[j_p] = n_p
            lm_in_graph[j_p] = True
            if cont_xy is not None:  # held by the continued graph, not by a prior
                xy_p = lm_xy[j_p] = cont_xy[j_p]
                fac_p = None
            add_value(LK(j_p), xy_p.copy())
            if fac_p is not None:
                add_factor(fac_p)
            out.map_fac.append(fac_p)
        if prior_kernel is None and out.cont is None:  # None: per-tree priors above
            out.joint_fac = joint_prior_factor(pmap, LK)
        if out.joint_fac is not None:
            add_factor(out.joint_fac)
    return out
