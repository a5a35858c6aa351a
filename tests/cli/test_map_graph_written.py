"""Which `stemmap map` runs write graph.npz (docs/outputs.md "graph.npz"): an isam2 run with
--gnss and one on a marginal prior map (per-tree or joint) write the graph that held them --
rebuilt alone from the file at its saved values it is at its optimum -- and `--prior-type
graph` continues each; --realtime writes none and says why (simulator, small)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.io.maps import read_trees_csv
from stemmap.slam._graph_continue import SavedGraph, read_graph


@pytest.fixture(scope="module")
def sim_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("graphwritten")
    args = ["sim", "scans", "--out", str(d / "run.npz"), "--seed", "3", "--n-scans", "300", "-q"]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    return d


def _map(d: Path, out: str, *extra: str) -> Any:
    args = ["map", str(d / "run.npz"), "--out", str(d / out), "--no-progress", *extra]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    return res


def _metrics(d: Path, out: str) -> dict[str, Any]:
    return dict(json.loads((d / out / "metrics.json").read_text()))


def _graph(folder: Path) -> SavedGraph:
    return read_graph(folder / "graph.npz", read_trees_csv(folder / "trees.csv"))


def _optimum_moves(folder: Path) -> tuple[float, float]:
    """The saved graph rebuilt alone (the factors a continuation adds, inflation 1) at its
    saved values, then Levenberg-Marquardt: how far (m) its poses and trees move."""
    import gtsam
    from gtsam.symbol_shorthand import L, V, W

    from stemmap.slam._graph_continue import ContinuedGraph
    from stemmap.slam.gnss import robust_kernel
    from stemmap.slam.graph import Isam2Config

    m = read_trees_csv(folder / "trees.csv")
    cfg = Isam2Config()
    kern = robust_kernel(gtsam, cfg.robust, cfg.robust_k)

    def noise(s: Any) -> Any:
        return gtsam.noiseModel.Robust.Create(kern, gtsam.noiseModel.Diagonal.Sigmas(s))

    cont = ContinuedGraph(_graph(folder), m, W, 1.0, vkey=V)
    graph = gtsam.NonlinearFactorGraph()
    for f in cont.factors(gtsam, L, noise):
        graph.add(f)
    vals = gtsam.Values()
    for k, v in cont.values(gtsam):
        vals.insert(k, v)
    for j, xy in enumerate(cont.tree_xy(len(m))):
        vals.insert(L(j), xy)
    res = gtsam.LevenbergMarquardtOptimizer(graph, vals).optimize()

    def pose_xy(v: Any) -> np.ndarray:
        return np.array([(v.atPose2(W(i)).x(), v.atPose2(W(i)).y()) for i in range(cont.n_poses)])

    def tree_xy(v: Any) -> np.ndarray:
        return np.array([v.atPoint2(L(j)) for j in range(len(m))])

    return (
        float(np.hypot(*(pose_xy(res) - pose_xy(vals)).T).max()),
        float(np.hypot(*(tree_xy(res) - tree_xy(vals)).T).max()),
    )


@pytest.mark.slow
def test_a_gnss_run_writes_its_graph_with_the_fixes(sim_log: Path) -> None:
    res = _map(sim_log, "gnss", "--gnss", str(sim_log / "run_gnss.csv"))
    assert "session graph (graph.npz)" in res.output and "written" in res.output
    g = _graph(sim_log / "gnss")
    sg = _metrics(sim_log, "gnss")["session_graph"]
    assert sg["written"] and sg["gnss_fixes"] == g.n_fixes
    assert g.n_fixes == _metrics(sim_log, "gnss")["backend_stats"]["gnss_fixes_fused"] > 2
    assert g.fix_robust == "cauchy" and (g.fix_sigma > 0).all()
    dp, dt = _optimum_moves(sim_log / "gnss")
    assert dp < 0.01 and dt < 0.02  # measured 0.9 / 3.5 mm (seed 3, 400 scans)
    _map(sim_log, "gnss2", "--gnss", str(sim_log / "run_gnss.csv"), "--prior-map",
         str(sim_log / "gnss"), "--prior-type", "graph")  # fmt: skip
    m2 = _metrics(sim_log, "gnss2")
    assert m2["relocalisation"]["graph_gnss_fixes"] == g.n_fixes
    assert m2["backend_stats"]["continued_gnss_fixes"] == g.n_fixes
    g2 = _graph(sim_log / "gnss2")  # both sessions' fixes, the earlier ones first
    assert g2.n_fixes == g.n_fixes + m2["backend_stats"]["gnss_fixes_fused"]
    np.testing.assert_array_equal(g2.fix_xy[: g.n_fixes], g.fix_xy)


@pytest.mark.slow
@pytest.mark.parametrize("prior_type", ["huber", "joint"])
def test_a_marginal_prior_run_writes_its_graph_with_the_priors(
    sim_log: Path, prior_type: str
) -> None:
    first = sim_log / "plain"
    if not first.is_dir():
        _map(sim_log, "plain")
    out = f"prior_{prior_type}"
    _map(sim_log, out, "--prior-map", str(first), "--start-guess", "0,0,0",
         "--prior-type", prior_type)  # fmt: skip
    g = _graph(sim_log / out)
    n1 = len(read_trees_csv(first / "trees.csv"))
    if prior_type == "huber":  # each prior tree by its robust prior, as this run held it
        assert g.tprior_tree.size == n1 and g.tprior_robust == "huber" and g.joint_tree.size == 0
    else:  # the joint information of trees_information.npz
        assert g.joint_tree.size == n1 and g.joint_sqrt.shape == (2 * n1, 2 * n1)
        assert g.tprior_tree.size == 0
    assert _metrics(sim_log, out)["session_graph"]["written"]
    dp, dt = _optimum_moves(sim_log / out)
    assert dp < 0.01 and dt < 0.02  # measured 0.3 / 5.5 mm
    # continued: the priors come along into the next graph
    nxt = f"{out}_cont"
    _map(sim_log, nxt, "--prior-map", str(sim_log / out), "--start-guess", "0,0,0",
         "--prior-type", "graph")  # fmt: skip
    g3 = _graph(sim_log / nxt)
    assert g3.tprior_tree.size == g.tprior_tree.size and g3.joint_tree.size == g.joint_tree.size
    assert g3.n_poses > g.n_poses


@pytest.mark.slow
def test_a_realtime_run_writes_no_graph_and_says_why(sim_log: Path) -> None:
    res = _map(sim_log, "rt", "--realtime")
    assert not (sim_log / "rt" / "graph.npz").exists()
    sg = _metrics(sim_log, "rt")["session_graph"]
    assert sg["written"] is False and "re-anchors" in sg["reason"]
    assert "no whole-session graph" in res.output
