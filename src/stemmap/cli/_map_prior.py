"""Map products of ``stemmap map`` that tie sessions and back-ends together: the prior map
(``--prior-map``: its session graph ``graph.npz`` continued, or its trees held by marginal
priors, with the joint information ``trees_information.npz`` when present), that graph and
joint information written beside trees.csv, and the ray-cast false-tree removal's report."""

from __future__ import annotations

import dataclasses
import json
import math
from enum import StrEnum
from pathlib import Path
from typing import Any

from stemmap.errors import ConfigError, InputError

__all__ = [
    "DEFAULT_PRIOR",
    "PriorMap",
    "PriorType",
    "check_gnss_frame",
    "continue_from_map",
    "false_trees_report",
    "gnss_start_check",
    "prior_map_frame",
    "read_prior_map",
    "session_graph_report",
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


@dataclasses.dataclass(frozen=True)
class PriorMap:
    """A ``--prior-map`` read and checked (:func:`read_prior_map`), ready for
    :func:`continue_from_map`: its trees (with their joint information when used), the saved
    session graph (``--prior-type graph``), the start guess and the note for metrics.json."""

    prior: Any
    guess: tuple[float, float, float] | None
    graph: Any
    note: dict[str, Any]


def read_prior_map(
    folder: Path,
    guess: str | None,
    backend: str,
    prior_type: PriorType | None = None,
) -> PriorMap:
    """``--prior-map``: read and check the map of ``folder`` (a map folder or its trees.csv)
    before any slow work (the command reads it before its first kernel call).

    ``prior_type`` ``graph``: the earlier session's graph (``graph.npz`` beside trees.csv) is
    continued (``SlamProblem.prior_graph``; a missing, damaged or mismatched ``graph.npz`` is
    an :class:`InputError`). Default (:data:`DEFAULT_PRIOR`): ``huber``, chosen by data.
    ``huber`` / ``cauchy``
    hold each prior tree by its own prior on its marginal with that robust loss; ``joint``
    makes the map's joint information (``trees_information.npz`` beside trees.csv) one joint
    prior over its trees, or without it each tree gets its own Gaussian prior (said in the
    note). The back-end must be built with ``prior_map_robust = prior_type.robust``.
    Either way the covariances are inflated by ``Isam2Config.prior_map_inflation``.
    """
    from stemmap.io.maps import TREES_INFORMATION_NPZ, read_trees_csv, read_trees_information
    from stemmap.slam._graph_continue import GRAPH_NPZ, read_graph
    from stemmap.slam.graph import Isam2Config

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
                "--backend isam2`, also with --gnss or on a marginal prior since format 2; not "
                "by other back-ends or --realtime); use --prior-type huber."
            )
        saved = read_graph(gfile, prior)  # InputError names the file and the problem
        note: dict[str, Any] = {
            "prior": "graph",
            "graph": str(gfile),
            "graph_poses": saved.n_poses,
            "graph_factors": saved.n_factors,
            "graph_gnss_fixes": saved.n_fixes,
            "prior_graph_inflation": Isam2Config().prior_graph_inflation,
        }
        return PriorMap(prior, g, saved, note)
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
    return PriorMap(prior, g, None, note)


def continue_from_map(problem: Any, prior_map: PriorMap) -> tuple[Any, Any, dict[str, Any]]:
    """Relocalise ``problem`` in ``prior_map`` (:func:`read_prior_map`): the problem (with
    the saved graph to continue, for ``--prior-type graph``), the relocalisation and a copy
    of the note."""
    from stemmap.slam.relocalise import continue_session

    problem, reloc = continue_session(problem, prior_map.prior, prior_map.guess)
    if prior_map.graph is not None:
        problem = dataclasses.replace(problem, prior_graph=prior_map.graph)
    return problem, reloc, dict(prior_map.note)


def prior_map_frame(folder: Path) -> dict[str, Any]:
    """What the map folder records about its frame: ``{"gnss_frame": bool | None, "crs": str
    | None, "from": file}``. ``metrics.json`` ``frames.gnss_frame`` (written since this check
    existed: true when the run fused ``--gnss`` or mapped on a GNSS-frame prior map) first,
    else ``run.json`` ``parameters.gnss`` (older maps: made with ``--gnss``), else unknown
    (``None``: a folder with neither, e.g. a hand-made trees.csv)."""
    d = folder if folder.is_dir() else folder.parent
    try:
        frames = json.loads((d / "metrics.json").read_text()).get("frames", {})
        if isinstance(frames, dict) and "gnss_frame" in frames:
            return {
                "gnss_frame": bool(frames["gnss_frame"]),
                "crs": frames.get("crs"),
                "from": str(d / "metrics.json"),
            }
    except (OSError, ValueError, AttributeError, RecursionError):
        pass
    try:
        par = json.loads((d / "run.json").read_text()).get("parameters", {})
        if isinstance(par, dict) and "gnss" in par:
            return {
                "gnss_frame": par["gnss"] is not None,
                "crs": par.get("crs"),
                "from": str(d / "run.json"),
            }
    except (OSError, ValueError, AttributeError, RecursionError):
        pass
    return {"gnss_frame": None, "crs": None, "from": None}


def check_gnss_frame(folder: Path, crs: str | None) -> dict[str, Any]:
    """``--gnss`` with ``--prior-map``: the prior map must be in the fixes' frame (its trees
    pin the graph in the map's frame; the relocalised start is kept,
    :func:`stemmap.slam.gnss.with_gnss_frame`). Return :func:`prior_map_frame` of ``folder``,
    or raise :class:`ConfigError` when it records no GNSS frame or another CRS than
    ``crs``."""
    rec = prior_map_frame(folder)
    if not folder.exists():  # continue_from_map names the missing map
        return rec
    fix = (
        "Make the prior map with --gnss (fixes in the same frame), or drop --gnss (the map's "
        "frame rules), or drop --prior-map."
    )
    if rec["gnss_frame"] is None:
        raise ConfigError(
            f"--gnss with --prior-map {folder}: the map folder records no frame (no metrics.json "
            f"frames.gnss_frame, no run.json), so the fixes cannot be known to share it. {fix}"
        )
    if not rec["gnss_frame"]:
        raise ConfigError(
            f"--gnss with --prior-map {folder}: that map was made without --gnss ({rec['from']}), "
            f"in its own odometry frame, not the fixes'. {fix}"
        )
    if rec["crs"] != crs:
        there = "no CRS (a local frame)" if rec["crs"] is None else f"CRS {rec['crs']}"
        here = "no --crs" if crs is None else f"--crs {crs}"
        want = "no --crs" if rec["crs"] is None else f"--crs {rec['crs']}"
        raise ConfigError(
            f"--gnss with --prior-map {folder}: the map has {there} ({rec['from']}), this run "
            f"{here}; the fixes must be in the map's frame: give {want} and fixes in it."
        )
    return rec


def gnss_start_check(problem: Any) -> dict[str, float]:
    """How far the relocalised start of ``problem`` (prior map + GNSS) is from the start
    aligned to its first fixes (:func:`stemmap.slam.gnss.gnss_initial_pose`): metrics.json
    ``relocalisation.gnss_start_offset_m`` / ``gnss_start_heading_deg``. Diagnostic only (the
    relocalised start is the one used); metres-large values mean the fixes and the map do not
    share a frame after all."""
    from stemmap.slam.gnss import gnss_initial_pose

    g = gnss_initial_pose(problem, problem.gnss)
    p = problem.initial_pose
    dth = math.remainder(float(g[2]) - float(p[2]), math.tau)
    return {
        "gnss_start_offset_m": round(math.hypot(g[0] - p[0], g[1] - p[1]), 3),
        "gnss_start_heading_deg": round(math.degrees(dth), 2),
    }


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


def session_graph_report(backend: str, realtime: bool, graph: Any) -> dict[str, Any]:
    """metrics.json ``session_graph``: whether ``graph.npz`` (the session graph a later
    ``--prior-map ... --prior-type graph`` continues) was written, and if not why."""
    from stemmap.slam._graph_continue import GRAPH_NPZ

    if graph is not None:
        return {
            "written": True, "file": GRAPH_NPZ, "poses": graph.n_poses,
            "factors": graph.n_factors, "gnss_fixes": graph.n_fixes,
            "tree_priors": int(graph.tprior_tree.size), "joint_prior": bool(graph.joint_tree.size),
        }  # fmt: skip
    if backend != "isam2":
        short = f"not written ({backend}: no factor graph)"
        why = f"the {backend} back-end keeps no factor graph (only isam2 does)"
    elif realtime:
        short = "not written (--realtime: no whole-session graph)"
        why = (
            "the realtime mapper re-anchors its smoother every few keyframes (bounded memory), "
            "so no graph of the whole session exists; continue this map with --prior-type "
            "huber, cauchy or joint"
        )
    else:
        short, why = "not written", "the back-end returned no graph"
    return {"written": False, "reason": why, "summary": short}


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
