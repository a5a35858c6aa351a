"""Continuing a saved session graph (stemmap.slam._graph_continue): save, read back, continue
on the simulator; a damaged or mismatched graph file is a clear InputError."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from _synthetic import loop_problem, split_problem

from stemmap.errors import InputError
from stemmap.slam._graph_continue import SavedGraph, read_graph, write_graph
from stemmap.slam.base import duplicate_pairs
from stemmap.slam.graph import Isam2Slam
from stemmap.slam.relocalise import continue_session
from stemmap.types import StemMap


@pytest.fixture(scope="module")
def sessions():
    """1.6 laps of the synthetic loop: session 1 (the first lap) mapped with its graph."""
    problem, truth, trees, _ = loop_problem(1, laps=1.6)
    p1, p2 = split_problem(problem, 52.0)
    r1 = Isam2Slam(export_graph=True).run(p1)
    f2 = int(np.searchsorted(problem.frames.times, p2.frames.times[0]))
    return p2, r1, truth, trees, f2


def test_saved_graph_round_trip(sessions, tmp_path: Path) -> None:
    _, r1, _, _, _ = sessions
    g = r1.graph
    assert isinstance(g, SavedGraph)
    # one pose per graph keyframe, the kept trees (trees.csv ids), every factor kind
    assert g.n_poses == r1.stats["keyframes_in_graph"]
    assert sorted(g.tree_ids.tolist()) == sorted(int(t.id) for t in r1.stem_map)
    np.testing.assert_allclose(
        g.trees[np.argsort(g.tree_ids)],
        r1.stem_map.xy[np.argsort([t.id for t in r1.stem_map])],
        atol=1e-9,
    )
    assert g.odo_ij.shape[0] >= g.n_poses - 1 - r1.stats["keyframes_anchored"]
    assert g.meas_pose.size > 5 * len(r1.stem_map) and g.prior_pose.tolist()[0] == 0
    write_graph(tmp_path / "graph.npz", g)
    back = read_graph(tmp_path / "graph.npz", r1.stem_map)
    for f in dataclasses.fields(SavedGraph):
        np.testing.assert_array_equal(getattr(back, f.name), getattr(g, f.name))


def test_continued_session_updates_the_earlier_trees(sessions) -> None:
    """Session 2 continues session 1's graph. One tree session 2 re-observes is put 0.45 m off
    the truth in the saved graph and its session-1 measurements dropped: only session 2's
    observations can bring it back. With the earlier trees held as variables it returns to
    within 0.2 m (session 2's own accuracy, ~0.1 m); were they frozen at their saved value (or
    held by a tight prior) it would stay 0.45 m off."""
    p2, r1, truth, trees, f2 = sessions
    g = r1.graph
    p2c, rel = continue_session(p2, r1.stem_map)
    assert rel.ok
    # the prior tree session 2 observes most often (slot j = row j of the prior map)
    first = Isam2Slam().run(dataclasses.replace(p2c, prior_graph=g))
    seen = [t for t in first.stem_map if int(t.id) < len(r1.stem_map)]
    j = int(max(seen, key=lambda t: t.n_obs - list(r1.stem_map)[int(t.id)].n_obs).id)
    row = int(np.flatnonzero(g.tree_ids == int(list(r1.stem_map)[j].id))[0])
    true_xy = trees[np.argmin(np.hypot(*(trees - g.trees[row]).T))]
    moved = g.trees.copy()
    moved[row] = true_xy + np.array([0.45, 0.0])
    keep = g.meas_tree != row
    bad = dataclasses.replace(
        g, trees=moved, meas_pose=g.meas_pose[keep], meas_tree=g.meas_tree[keep], meas=g.meas[keep]
    )
    res = Isam2Slam(export_graph=True).run(dataclasses.replace(p2c, prior_graph=bad))
    est = next(t for t in res.stem_map if int(t.id) == j)
    assert np.hypot(est.x - true_xy[0], est.y - true_xy[1]) < 0.2
    # session 2 itself lands in the session-1 frame, one merged map
    err = np.hypot(*(res.trajectory.xy - truth[f2:, :2]).T)
    assert math.sqrt(np.mean(err**2)) < 0.3
    assert duplicate_pairs(res.stem_map, 1.0) <= 2
    assert res.stats["continued_poses"] == g.n_poses
    # its own saved graph holds both sessions: session 1's poses first, then its keyframes;
    # the earlier poses are variables (the re-estimate moves them, a little)
    g2 = res.graph
    assert g2.n_poses == g.n_poses + res.stats["keyframes_in_graph"]
    assert g2.tree_ids.size == len(res.stem_map)
    dp = np.hypot(*(g2.poses[: g.n_poses, :2] - g.poses[:, :2]).T)
    assert 0.0 < dp.max() < 0.5
    # and pose covariances still come out for every frame (two chains, W then X)
    assert res.pose_covs is not None and np.isfinite(res.pose_covs).all()


def _save_bad(tmp_path: Path, g: SavedGraph, **arrays: object) -> Path:
    write_graph(tmp_path / "graph.npz", g)
    with np.load(tmp_path / "graph.npz") as z:
        data = {k: z[k] for k in z.files}
    data.update(arrays)
    np.savez(tmp_path / "graph.npz", **data)
    return tmp_path / "graph.npz"


def test_a_damaged_or_mismatched_graph_file_is_an_input_error(sessions, tmp_path: Path) -> None:
    _, r1, _, _, _ = sessions
    g = r1.graph
    p = tmp_path / "graph.npz"
    p.write_bytes(b"PK\x03\x04 not a zip archive")
    with pytest.raises(InputError, match="damaged or not a stemmap graph"):
        read_graph(p)
    p.write_bytes(p.read_bytes()[:0])
    with pytest.raises(InputError, match=r"graph\.npz"):
        read_graph(p)
    with pytest.raises(InputError, match="version 99"):
        read_graph(_save_bad(tmp_path, g, format_version=np.array(99)))
    with pytest.raises(InputError, match="format 'other'"):
        read_graph(_save_bad(tmp_path, g, format=np.array("other")))
    with pytest.raises(InputError, match="meas_tree indexes outside"):
        read_graph(_save_bad(tmp_path, g, meas_tree=g.meas_tree + 10_000))
    with pytest.raises(InputError, match="poses has non-finite"):
        read_graph(_save_bad(tmp_path, g, poses=np.full_like(g.poses, np.nan)))
    with pytest.raises(InputError, match="odo_cov has shape"):
        read_graph(_save_bad(tmp_path, g, odo_cov=g.odo_cov[:, :2]))
    data = _save_bad(tmp_path, g)
    with np.load(data) as z:
        short = {k: z[k] for k in z.files if k != "meas"}
    np.savez(data, **short)
    with pytest.raises(InputError, match=r"damaged.*meas is not"):
        read_graph(data)
    # a graph of another map (tree ids differ from the trees.csv beside it)
    other = StemMap(tuple(dataclasses.replace(t, id=int(t.id) + 1000) for t in r1.stem_map))
    write_graph(p, g)
    with pytest.raises(InputError, match="ids differ"):
        read_graph(p, other)


def test_a_version_1_file_is_still_read(sessions, tmp_path: Path) -> None:
    """Format 2 added the GNSS fixes and the prior map's tree priors; a version-1 archive
    (without those arrays) reads as a graph with none of them. A kernel name the reader does
    not know is an input error."""
    from stemmap.slam._graph_continue import _V2_FIELDS, _V2_SCALARS

    _, r1, _, _, _ = sessions
    g = r1.graph
    p = _save_bad(tmp_path, g, format_version=np.array(1))
    with np.load(p) as z:
        v1 = {k: z[k] for k in z.files if k not in (*_V2_FIELDS, *_V2_SCALARS)}
    np.savez(p, **v1)
    back = read_graph(p, r1.stem_map)
    assert back.n_fixes == 0 and back.tprior_tree.size == 0 and back.joint_tree.size == 0
    np.testing.assert_array_equal(back.meas, g.meas)
    with pytest.raises(InputError, match="tprior_robust is 'tukey'"):
        read_graph(_save_bad(tmp_path, g, tprior_robust=np.array("tukey")))
