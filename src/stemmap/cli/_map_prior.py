"""Map products of ``stemmap map`` that tie sessions and back-ends together: the prior map
(``--prior-map``: its session graph ``graph.npz`` continued, or its trees held by marginal
priors, with the joint information ``trees_information.npz`` when present), that graph and
joint information written beside trees.csv, and the ray-cast false-tree removal's report."""

from __future__ import annotations

import dataclasses
import math
from enum import StrEnum
from pathlib import Path
from typing import Any

from stemmap.errors import ConfigError, InputError

__all__ = [
    "DEFAULT_PRIOR",
    "PriorType",
    "continue_from_map",
    "false_trees_report",
    "write_information",
]


class PriorType(StrEnum):
    """``--prior-type``: how the prior map enters the graph -- ``graph``: its session graph
    continued (:mod:`stemmap.slam._graph_continue`); else its trees by marginal priors
    (``Isam2Config.prior_map_robust``)."""

    graph = "graph"
    huber = "huber"
    cauchy = "cauchy"
    joint = "joint"

    @property
    def robust(self) -> str:
        """The ``Isam2Config.prior_map_robust`` value: ``"none"`` for the joint prior (and
        unused by ``graph``: the default, Huber)."""
        return {"joint": "none", "graph": "huber"}.get(self.value, self.value)


#: ``--prior-type`` when none is given, with or without a ``graph.npz`` in the map folder:
#: the marginal prior with per-tree Huber losses. Chosen on the 400-s and 800-s Victoria Park
#: session pairs (session 2 1.256 / 1.444 m against the continued graph's 1.282 / 1.446 m at
#: its best inflation); docs/algorithms/slam.md "Continuing the saved graph".
DEFAULT_PRIOR = PriorType.huber


def continue_from_map(
    problem: Any,
    folder: Path,
    guess: str | None,
    backend: str,
    prior_type: PriorType | None = None,
) -> tuple[Any, Any, dict[str, Any]]:
    """``--prior-map``: relocalise ``problem`` in the map of ``folder`` (library call).

    ``prior_type`` ``graph``: the earlier session's graph (``graph.npz`` beside trees.csv) is
    continued (``SlamProblem.prior_graph``; a missing, damaged or mismatched ``graph.npz`` is
    an :class:`InputError`). Default (:data:`DEFAULT_PRIOR`): ``huber``, chosen by data.
    ``huber`` / ``cauchy``
    hold each prior tree by its own prior on its marginal with that robust loss; ``joint``
    makes the map's joint information (``trees_information.npz`` beside trees.csv) one joint
    prior over its trees, or without it each tree gets its own Gaussian prior (said in the
    returned note). The back-end must be built with ``prior_map_robust = prior_type.robust``.
    Either way the covariances are inflated by ``Isam2Config.prior_map_inflation``.
    """
    from stemmap.io.maps import TREES_INFORMATION_NPZ, read_trees_csv, read_trees_information
    from stemmap.slam._graph_continue import GRAPH_NPZ, read_graph
    from stemmap.slam.graph import Isam2Config
    from stemmap.slam.relocalise import continue_session

    if backend != "isam2":
        raise ConfigError(f"--prior-map is used by the isam2 back-end only; got {backend}.")
    g = None
    if guess is not None:
        try:
            gx, gy, gd = (float(v) for v in guess.split(","))
        except ValueError as exc:
            raise ConfigError(f"--start-guess must be 'x,y,heading_deg', got {guess!r}.") from exc
        g = (gx, gy, math.radians(gd))
    csv = folder / "trees.csv" if folder.is_dir() else folder
    prior = read_trees_csv(csv)
    npz = csv.with_name(TREES_INFORMATION_NPZ)
    gfile = csv.with_name(GRAPH_NPZ)
    if prior_type is None:
        prior_type = DEFAULT_PRIOR
    if prior_type is PriorType.graph:
        if not gfile.is_file():
            raise InputError(
                f"--prior-type graph: no {GRAPH_NPZ} beside {csv} (written by `stemmap map "
                "--backend isam2` since format 1; not by other back-ends, --realtime, GNSS "
                "runs or runs on a marginal prior); use --prior-type huber."
            )
        saved = read_graph(gfile, prior)  # InputError names the file and the problem
        problem, reloc = continue_session(problem, prior, g)
        note: dict[str, Any] = {
            "prior": "graph",
            "graph": str(gfile),
            "graph_poses": saved.n_poses,
            "graph_factors": int(saved.odo_ij.shape[0] + saved.meas_pose.shape[0]),
            "prior_graph_inflation": Isam2Config().prior_graph_inflation,
        }
        return dataclasses.replace(problem, prior_graph=saved), reloc, note
    cfg = Isam2Config()
    robust = prior_type.robust
    if robust != "none":
        note = {
            "prior": f"per-tree {robust}",
            "note": f"each prior tree held by its own robust ({robust}) prior on its marginal "
            f"(--prior-type); {TREES_INFORMATION_NPZ}, if present, is not used",
        }
    elif npz.is_file():
        prior = read_trees_information(npz, prior)
        note = {"prior": "joint", "information": str(npz)}
    else:
        note = {
            "prior": "per-tree",
            "note": f"no {TREES_INFORMATION_NPZ} beside {csv.name}: independent per-tree priors "
            "(the correlations between the prior map's trees are lost)",
        }
    note["prior_map_inflation"] = cfg.prior_map_inflation
    note["graph_unused"] = (
        f"{GRAPH_NPZ} present, not used with --prior-type {prior_type} (--prior-type graph "
        "continues it)"
        if gfile.is_file()
        else f"no {GRAPH_NPZ} beside {csv.name}: marginal prior"
    )
    problem, reloc = continue_session(problem, prior, g)
    return problem, reloc, note


def write_information(stage: Path, stem_map: Any, graph: Any = None) -> list[str]:
    """``trees_information.npz`` beside trees.csv when the map has a joint information, and
    ``graph.npz`` when the back-end returned its session graph (``SlamResult.graph``)."""
    from stemmap.io.maps import TREES_INFORMATION_NPZ, write_trees_information
    from stemmap.slam._graph_continue import GRAPH_NPZ, write_graph

    names = []
    if stem_map.information is not None:
        write_trees_information(stage / TREES_INFORMATION_NPZ, stem_map)
        names.append(TREES_INFORMATION_NPZ)
    if graph is not None:
        write_graph(stage / GRAPH_NPZ, graph)
        names.append(GRAPH_NPZ)
    return names


_NO_SCANS = {
    "victoria-park": "Victoria Park has no raw laser ranges (only the trunk detections)",
    "detections": "a detections CSV has no raw laser ranges",
    "frames": "a frames bundle has no 2D laser scans",
}


def false_trees_report(backend: str, stats: dict[str, Any], kind: str) -> dict[str, Any]:
    """metrics.json ``false_trees``: what the ray-cast false-tree removal (Öhman) did."""
    if backend != "forestrix":
        return {"ran": False, "reason": f"the {backend} back-end has no false-tree removal"}
    mode = str(stats.get("false_trees", ""))
    if mode.startswith("skipped"):
        why = _NO_SCANS.get(kind, "the input has no raw scans")
        return {"ran": False, "method": "rays", "reason": why}
    if mode == "none":
        return {"ran": False, "method": "none", "reason": "switched off"}
    return {"ran": True, "method": mode, "removed": int(stats.get("false_trees_removed", 0))}
