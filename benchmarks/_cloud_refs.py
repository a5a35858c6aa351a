"""Fixed ring references of the real clouds (cloud_real.py, cloud_robustness.py).

The references are full-ring circle fits of each cloud's own points at breast height
(:func:`stemmap.cloud.reference.converged_ring_reference`: 15 start circles about a seed,
the median and the spread of the fits). The seeds -- one circle and ring height per stem --
are read from the committed ``_cloud_ring_seeds.json``, not from the detector being scored,
so a detector change moves the measured DBH and never the yardstick. Detections are paired
with the references by position (:func:`match_stems`).

The seeds file was written once by ``python benchmarks/_cloud_refs.py --write`` (2026-12-04,
main at 3e5ad33): preset ``ours`` with heights on, as cloud_real.py; per detected stem the
converged ring started from the detected circle, and its own circle (not the detector's)
is the seed. Stems without a ring fit (too few points at breast height) have no seed. To
check a file against the clouds: ``python benchmarks/_cloud_refs.py`` (prints the references).
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from _datasets import require_datasets_dir
from stemmap.cloud.reference import RingReference, converged_ring_reference
from stemmap.cloud.result import BASE_SLICE
from stemmap.io.clouds import read_cloud

SEEDS_FILE = Path(__file__).resolve().parent / "_cloud_ring_seeds.json"

CLOUDS = {
    "treels_spruce": "treels/spruce.laz",
    "treels_pine": "treels/pine.laz",
    "treels_pine_plot": "treels/pine_plot.laz",
    "archi_tree_1": "archi/Tree_1_point_cloud.las",
    "archi_tree_2": "archi/Tree_2_point_cloud.las",
    "lidr_dbh": "lidr_dbh/dbh.laz",
    "fortls_slice": "fortls_slice/diameters.laz",
}


@dataclass(frozen=True)
class RingSeed:
    """Where to fit one stem's reference ring: centre ``x, y`` (m), ring height ``z`` (m,
    the cloud's frame), start radius ``r`` (m) and the ring's ``half`` thickness (m)."""

    x: float
    y: float
    z: float
    r: float
    half: float


def load_seeds(path: Path = SEEDS_FILE) -> dict[str, list[RingSeed]]:
    """The seeds of every cloud, by cloud key (as :data:`CLOUDS`)."""
    data = json.loads(path.read_text())
    return {
        k: [RingSeed(*map(float, s), half=float(c["half_thickness_m"])) for s in c["stems"]]
        for k, c in data["clouds"].items()
    }


def seeded_reference(
    xyz: np.ndarray, seed: RingSeed, z: float | None = None
) -> RingReference | None:
    """The converged ring of one seed (at ``z`` instead of the seed's height if given)."""
    return converged_ring_reference(
        xyz, (seed.x, seed.y), seed.z if z is None else z, seed.r, half_thickness=seed.half
    )


#: height step (m) of :func:`tracked_reference`: a stem leaning 10 degrees moves its centre by
#: 1.8 cm per step, well inside the start ring's 30 % of the radius
TRACK_STEP = 0.1


def tracked_reference(xyz: np.ndarray, seed: RingSeed, z: float) -> RingReference | None:
    """The converged ring of ``seed``'s stem at height ``z``, followed up (or down) from the
    seed's own height in steps of :data:`TRACK_STEP`: each ring starts from the previous
    one's circle, so a leaning or tapering stem is followed without reading the detector
    (only the height ``z`` is given). A step with no ring (occlusion) keeps the previous
    start. None when the ring at ``z`` does not converge."""
    n = max(1, int(np.ceil(abs(z - seed.z) / TRACK_STEP - 1e-9)))
    cx, cy, r = seed.x, seed.y, seed.r
    ring = None
    for h in np.linspace(seed.z, z, n + 1)[1:]:
        ring = converged_ring_reference(xyz, (cx, cy), float(h), r, half_thickness=seed.half)
        if ring is not None:
            cx, cy, r = ring.x, ring.y, ring.diameter / 2
    return ring


def fixed_references(xyz: np.ndarray, seeds: list[RingSeed]) -> list[RingReference | None]:
    """The reference of every seed of one cloud, in the seeds' order."""
    return [seeded_reference(xyz, s) for s in seeds]


def match_stems(base_xy: np.ndarray, base_d: np.ndarray, xy: np.ndarray) -> list[tuple[int, int]]:
    """Greedy nearest pairs (base, detection) within half the base diameter + 10 cm."""
    base_xy = np.asarray(base_xy, dtype=np.float64).reshape(-1, 2)
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if base_xy.shape[0] == 0 or xy.shape[0] == 0:
        return []
    d = np.hypot(*(base_xy[:, None, :] - xy[None, :, :]).transpose(2, 0, 1))
    pairs: list[tuple[int, int]] = []
    used_b: set[int] = set()
    used_d: set[int] = set()
    for flat in np.argsort(d, axis=None):
        i, j = divmod(int(flat), xy.shape[0])
        if i in used_b or j in used_d or d[i, j] > 0.5 * base_d[i] + 0.1:
            continue
        pairs.append((i, j))
        used_b.add(i)
        used_d.add(j)
    return pairs


def reference_of_each(
    refs: list[RingReference | None], xy: np.ndarray
) -> list[tuple[int, RingReference] | None]:
    """For each detection at ``xy`` (the cloud's frame): (index, reference) of the fixed
    reference it pairs with (:func:`match_stems`), or None."""
    have = [(k, r) for k, r in enumerate(refs) if r is not None]
    out: list[tuple[int, RingReference] | None] = [None] * np.asarray(xy).reshape(-1, 2).shape[0]
    if not have:
        return out
    rxy = np.array([[r.x, r.y] for _, r in have])
    rd = np.array([r.diameter for _, r in have])
    for a, j in match_stems(rxy, rd, xy):
        out[j] = have[a]
    return out


def _write(root: Path) -> dict[str, Any]:
    from stemmap.cloud.stems import StemConfig, detect_stems_file

    clouds: dict[str, Any] = {}
    for key, rel in CLOUDS.items():
        xyz = read_cloud(root / rel).xyz
        det = detect_stems_file(root / rel, replace(StemConfig(), estimate_height=True))
        half = 0.05 if det.spacing < 0.03 else 0.1
        z_slice = float(np.median(xyz[:, 2]))
        stems = []
        for i in range(len(det)):
            z = z_slice if det.base == BASE_SLICE else float(det.z[i])
            s = RingSeed(float(det.xy[i, 0]), float(det.xy[i, 1]), z, det.diameter[i] / 2, half)
            ref = seeded_reference(xyz, s)
            if ref is not None:
                stems.append(
                    [round(ref.x, 3), round(ref.y, 3), round(z, 3), round(ref.diameter / 2, 3)]
                )
        clouds[key] = {"half_thickness_m": half, "stems": stems}
    return clouds


def _dump(clouds: dict[str, Any]) -> str:
    """One line per stem, so that a review sees each seed."""
    lines = [
        "{",
        ' "note": "ring-reference seeds [x, y, z, r] (m, the cloud\'s frame) per stem; written by '
        "python benchmarks/_cloud_refs.py --write (benchmarks/_cloud_refs.py); the benchmarks' "
        'references converge from these, never from the detector",',
        ' "clouds": {',
    ]
    for n, (key, c) in enumerate(clouds.items()):
        rows = ",\n".join(f"    {json.dumps(s)}" for s in c["stems"])
        tail = "," if n < len(clouds) - 1 else ""
        lines.append(f'  "{key}": {{"half_thickness_m": {c["half_thickness_m"]}, "stems": [')
        lines.append(rows)
        lines.append(f"  ]}}{tail}")
    lines += [" }", "}", ""]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--write", action="store_true", help="rewrite the seeds from the detector")
    args = ap.parse_args()
    root = require_datasets_dir()
    if args.write:
        SEEDS_FILE.write_text(_dump(_write(root)))
    out = {}
    for key, seeds in load_seeds().items():
        xyz = read_cloud(root / CLOUDS[key]).xyz
        out[key] = [
            None
            if r is None
            else {
                "dbh_cm": round(100 * r.diameter, 2),
                "spread_cm": round(100 * r.spread, 2),
                "rms_cm": round(100 * r.rms, 2),
                "arc_deg": round(r.arc_deg),
                "full": r.full,
            }
            for r in fixed_references(xyz, seeds)
        ]
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
