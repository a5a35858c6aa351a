"""Map products of ``stemmap map`` that tie sessions and back-ends together: the prior map
(``--prior-map``, with its joint information ``trees_information.npz`` when present), that
joint information written beside trees.csv, and the ray-cast false-tree removal's report."""

from __future__ import annotations

import math
from enum import StrEnum
from pathlib import Path
from typing import Any

from stemmap.errors import ConfigError

__all__ = ["PriorType", "continue_from_map", "false_trees_report", "write_information"]


class PriorType(StrEnum):
    """``--prior-type``: how the prior map's trees enter the graph
    (``Isam2Config.prior_map_robust``)."""

    huber = "huber"
    cauchy = "cauchy"
    joint = "joint"

    @property
    def robust(self) -> str:
        """The ``Isam2Config.prior_map_robust`` value: ``"none"`` for the joint prior."""
        return "none" if self is PriorType.joint else self.value


def continue_from_map(
    problem: Any,
    folder: Path,
    guess: str | None,
    backend: str,
    prior_type: PriorType | None = None,
) -> tuple[Any, Any, dict[str, Any]]:
    """``--prior-map``: relocalise ``problem`` in the map of ``folder`` (library call).

    ``prior_type`` (default: ``Isam2Config.prior_map_robust``, Huber): ``huber`` / ``cauchy``
    hold each prior tree by its own prior on its marginal with that robust loss; ``joint``
    makes the map's joint information (``trees_information.npz`` beside trees.csv) one joint
    prior over its trees, or without it each tree gets its own Gaussian prior (said in the
    returned note). The back-end must be built with ``prior_map_robust = prior_type.robust``.
    Either way the covariances are inflated by ``Isam2Config.prior_map_inflation``.
    """
    from stemmap.io.maps import TREES_INFORMATION_NPZ, read_trees_csv, read_trees_information
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
    cfg = Isam2Config()
    robust = cfg.prior_map_robust if prior_type is None else prior_type.robust
    if robust != "none":
        note: dict[str, Any] = {
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
    problem, reloc = continue_session(problem, prior, g)
    return problem, reloc, note


def write_information(stage: Path, stem_map: Any) -> list[str]:
    """``trees_information.npz`` beside trees.csv when the map has a joint information."""
    from stemmap.io.maps import TREES_INFORMATION_NPZ, write_trees_information

    if stem_map.information is None:
        return []
    write_trees_information(stage / TREES_INFORMATION_NPZ, stem_map)
    return [TREES_INFORMATION_NPZ]


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
