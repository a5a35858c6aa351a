"""`stemmap map` wiring: raw scans reach Forestrix's ray-cast false-tree removal; the isam2
map's joint information goes to trees_information.npz and back in through --prior-map."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.io.maps import read_trees_csv, read_trees_information
from stemmap.types import StemMap, Tree


@pytest.fixture(scope="module")
def sim_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("simlog")
    args = ["sim", "scans", "--out", str(d / "run.npz"), "--seed", "2", "--n-scans", "400", "-q"]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    return d


def _metrics(out: Path) -> dict[str, Any]:
    return dict(json.loads((out / "metrics.json").read_text()))


@pytest.mark.slow
def test_forestrix_cli_removes_injected_false_trees_with_the_raw_scans(
    sim_log: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Two phantom trees are put ON the driven path (free space: the vehicle drove through
    them, earlier scans' rays pass through them) into Forestrix's output map. Only the raw-ray
    removal can delete them, and it runs only when the CLI passes the scans."""
    from stemmap.slam.forestrix import ForestrixSlam

    orig = ForestrixSlam._output_map
    injected: list[np.ndarray] = []

    def with_phantoms(self: ForestrixSlam, st: Any) -> tuple[StemMap, int]:
        sm, n = orig(self, st)
        poses = np.asarray(st.poses)
        xy = poses[[len(poses) // 2, (3 * len(poses)) // 4], :2]
        injected.append(xy)
        k = 1 + max((t.id for t in sm), default=0)
        ghosts = tuple(
            Tree(id=k + i, x=float(p[0]), y=float(p[1]), diameter=0.25, n_obs=50)
            for i, p in enumerate(xy)
        )
        return StemMap(sm.trees + ghosts), n

    monkeypatch.setattr(ForestrixSlam, "_output_map", with_phantoms)
    out = sim_log / "m_forestrix"
    res = CliRunner().invoke(
        app, ["map", str(sim_log / "run.npz"), "--backend", "forestrix", "--out", str(out)]
    )
    assert res.exit_code == 0, res.output
    m = _metrics(out)
    assert m["backend_stats"]["false_trees"] == "rays"
    assert m["false_trees"]["ran"] is True
    assert m["false_trees"]["removed"] >= 2
    assert m["false_trees"]["removed"] == m["backend_stats"]["false_trees_removed"]
    xy = read_trees_csv(out / "trees.csv").xy
    for p in injected[0]:  # 0.1 m: the phantoms sit exactly there (no re-estimation after)
        assert np.hypot(*(xy - p).T).min() > 0.1
    assert len(xy) >= 5  # the real trees stay


@pytest.mark.slow
def test_forestrix_cli_says_why_removal_was_skipped_on_detections(sim_log: Path) -> None:
    run = CliRunner()
    det = sim_log / "det.csv"
    assert run.invoke(app, ["detect", str(sim_log / "run.npz"), "--out", str(det)]).exit_code == 0
    out = sim_log / "m_det"
    args = ["map", str(det), "--backend", "forestrix", "--out", str(out)]
    res = run.invoke(app, [*args, "--odometry", str(sim_log / "run_odometry.csv")])
    assert res.exit_code == 0, res.output
    ft = _metrics(out)["false_trees"]
    assert ft["ran"] is False and "detections CSV" in ft["reason"]


@pytest.mark.slow
def test_prior_map_uses_the_joint_information(
    sim_log: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    run = CliRunner()
    first = sim_log / "m_isam2"
    res = run.invoke(app, ["map", str(sim_log / "run.npz"), "--out", str(first)])
    assert res.exit_code == 0, res.output
    npz = first / "trees_information.npz"
    assert npz.is_file()
    outputs = json.loads((first / "run.json").read_text())["outputs"]
    assert "trees_information.npz" in {o["path"] for o in outputs}  # in the manifest
    sm = read_trees_information(npz, read_trees_csv(first / "trees.csv"))
    info = np.asarray(sm.information)
    assert info.shape == (2 * len(sm), 2 * len(sm))
    assert np.allclose(info, info.T, atol=1e-9 * np.abs(info).max())
    assert np.linalg.eigvalsh(info).min() > 0  # a usable (positive definite) prior
    # the marginal of each tree from the joint information = the trees.csv covariance
    cov = np.linalg.inv(info)
    for j, t in enumerate(sm):
        c = cov[2 * j : 2 * j + 2, 2 * j : 2 * j + 2]
        assert np.allclose(np.sqrt(np.diag(c)), np.sqrt(np.diag(t.cov)), rtol=0.05)

    import stemmap.slam._graph_session as session

    used: list[bool] = []
    orig = session.joint_prior_factor

    def spy(*a: Any, **k: Any) -> Any:
        f = orig(*a, **k)
        used.append(f is not None)
        return f

    monkeypatch.setattr(session, "joint_prior_factor", spy)
    second = sim_log / "m_isam2_prior"
    args = ["map", str(sim_log / "run.npz"), "--prior-map", str(first), "--out", str(second)]
    args += ["--start-guess", "0,0,0"]
    # --prior-type huber (Isam2Config.prior_map_robust = "huber"; the default without a
    # graph.npz): per-tree robust priors, the joint information and the graph are not used,
    # and metrics.json says so
    res = run.invoke(app, [*args, "--prior-type", "huber"])
    assert res.exit_code == 0, res.output
    assert not any(used)  # no joint prior factor built
    rl = _metrics(second)["relocalisation"]
    assert rl["prior"] == "per-tree huber" and "not used" in rl["note"]
    assert "graph.npz present" in rl["graph_unused"]

    # --prior-type joint (Isam2Config.prior_map_robust = "none"): the joint prior factor
    # reaches the graph
    used.clear()
    joint = sim_log / "m_isam2_joint"
    args[args.index(str(second))] = str(joint)
    args += ["--prior-type", "joint"]
    res = run.invoke(app, args)
    assert res.exit_code == 0, res.output
    assert used and used[0]
    rl = _metrics(joint)["relocalisation"]
    assert rl["prior"] == "joint" and rl["prior_map_inflation"] == 4.0

    npz.unlink()  # without it: per-tree Gaussian priors, and said so
    used.clear()
    third = sim_log / "m_isam2_pertree"
    args[args.index(str(joint))] = str(third)
    res = run.invoke(app, args)
    assert res.exit_code == 0, res.output
    assert used and not any(used)
    rl = _metrics(third)["relocalisation"]
    assert rl["prior"] == "per-tree" and "trees_information.npz" in rl["note"]


@pytest.mark.slow
def test_prior_map_continues_the_saved_graph(sim_log: Path) -> None:
    """The map folder carries graph.npz (in the manifest); --prior-type graph continues it
    (metrics.json says so) and writes the merged map and the merged graph; the default (the
    marginal prior) says it left graph.npz unused; a damaged or mismatched graph.npz is one
    clear error line; an old folder without it still loads (the marginal prior)."""
    from stemmap.slam._graph_continue import read_graph

    run = CliRunner()
    first = sim_log / "g_first"
    res = run.invoke(app, ["map", str(sim_log / "run.npz"), "--out", str(first)])
    assert res.exit_code == 0, res.output
    outputs = {o["path"] for o in json.loads((first / "run.json").read_text())["outputs"]}
    assert "graph.npz" in outputs
    m1 = read_trees_csv(first / "trees.csv")
    g1 = read_graph(first / "graph.npz", m1)

    def cont(prior: Path, out: str, *extra: str) -> Any:
        args = ["map", str(sim_log / "run.npz"), "--prior-map", str(prior), "--start-guess"]
        return run.invoke(app, [*args, "0,0,0", *extra, "--out", str(sim_log / out)])

    res = cont(first, "g_second", "--prior-type", "graph")
    assert res.exit_code == 0, res.output
    second = sim_log / "g_second"
    rl = _metrics(second)["relocalisation"]
    assert rl["ok"] and rl["prior"] == "graph" and rl["graph_poses"] == g1.n_poses
    m2 = read_trees_csv(second / "trees.csv")
    assert len(m2) >= len(m1)  # the merged map: session 1's trees kept, updated
    g2 = read_graph(second / "graph.npz", m2)  # the merged graph: both sessions' poses
    assert g2.n_poses > g1.n_poses

    res = cont(second, "g_default")  # the default: the marginal prior, graph.npz unused
    assert res.exit_code == 0, res.output
    rl = _metrics(sim_log / "g_default")["relocalisation"]
    assert rl["prior"] == "per-tree huber" and "graph.npz present" in rl["graph_unused"]

    (second / "graph.npz").write_bytes(b"not an archive")
    res = cont(second, "g_bad", "--prior-type", "graph")
    assert res.exit_code != 0
    err = [ln for ln in res.output.splitlines() if ln.startswith("error:")]
    assert len(err) == 1 and "graph.npz" in err[0] and "damaged" in err[0], res.output
    # a graph.npz of another map beside this trees.csv (ids differ). Made explicit (Dec 6):
    # the test copied session 1's graph, whose ids differed only while session 2 added a
    # tree, which the simulated log stopped giving when the SICK's threshold became 0.3
    with np.load(first / "graph.npz") as z:
        arrays = {k: z[k] for k in z.files}
    arrays["tree_ids"] = arrays["tree_ids"] + 1 + int(arrays["tree_ids"].max())
    np.savez(second / "graph.npz", **arrays)
    res = cont(second, "g_bad2", "--prior-type", "graph")
    assert res.exit_code != 0 and "ids differ" in res.output, res.output

    (second / "graph.npz").unlink()  # an old map folder: the marginal prior, said so
    res = cont(second, "g_third")
    assert res.exit_code == 0, res.output
    rl = _metrics(sim_log / "g_third")["relocalisation"]
    assert rl["prior"] == "per-tree huber" and "no graph.npz" in rl["graph_unused"]
    res = cont(second, "g_bad3", "--prior-type", "graph")
    assert res.exit_code != 0 and "no graph.npz" in res.output, res.output


def test_prior_type_needs_a_prior_map(sim_log: Path) -> None:
    args = ["map", str(sim_log / "run.npz"), "--prior-type", "cauchy"]
    res = CliRunner().invoke(app, [*args, "--out", str(sim_log / "m_no_prior")])
    assert res.exit_code != 0
    assert "--prior-type needs --prior-map" in res.output
