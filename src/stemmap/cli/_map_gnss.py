"""``stemmap map --gnss``: the GNSS-frame track, the path as the GNSS receiver reads it.

``trajectory.csv`` is the tree-consistent path (use it with the map). Next to it ``--gnss``
writes ``trajectory_gnss.csv`` (``trajectory_gnss.tum`` with ``--trajectory-format tum``): the
same path plus the fused fixes' slowly varying offset (:mod:`stemmap.slam.gnss_track`), i.e.
where this receiver will say the vehicle is -- follow it to drive to GNSS waypoints. The
offset's Gauss-Markov model is estimated from the run's own fixes
(:func:`stemmap.slam.gnss_track.fit_gnss_offset_model`) and the offset smoothed over the whole
run (an offline product: the fixes on both sides of a moment count). With ``--gpkg`` the track
is also in ``map.gpkg`` (layers ``trajectory_gnss``, ``poses_gnss``); with ``--crs`` also
``trajectory_gnss.geojson`` (RFC 7946 points). Too few fixes to estimate the model: a warning,
no track files, and the reason in metrics.json ``gnss_track``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["GnssTrack", "gnss_track", "gnss_track_layers", "write_gnss_track"]

#: what the track is, in metrics.json and the GeoJSON
MEANING = (
    "the path as the GNSS receiver would read it: trajectory.csv plus the fused fixes' "
    "smoothed slowly varying offset (follows the receiver's correlated error; use it to drive "
    "to GNSS waypoints); trajectory.csv is the tree-consistent path (use it with the map)"
)


@dataclass(frozen=True, eq=False)
class GnssTrack:
    """The GNSS-frame track of a run: ``trajectory`` (poses), ``std`` (N,) m the per-axis
    1-sigma of its position (the offset estimate's), ``covs`` (N, 3, 3) for the CSV (position
    block ``std²`` I, heading variance the path's, cross terms 0), ``record`` for
    metrics.json."""

    trajectory: Any
    std: np.ndarray
    covs: np.ndarray
    record: dict[str, Any]


def gnss_track(problem: Any, result: Any) -> tuple[GnssTrack | None, dict[str, Any]]:
    """The track of ``result`` (a run with ``problem.gnss``), or None and why (logged as a
    warning on stderr) when the fixes are too few to estimate the offset model."""
    from stemmap.cli._common import console
    from stemmap.errors import InputError
    from stemmap.slam.gnss_track import fit_gnss_offset_model, gnss_frame_trajectory, gnss_offset

    tr, fixes = result.trajectory, problem.gnss
    try:
        model = fit_gnss_offset_model(tr, fixes)
    except InputError as exc:
        console.print(f"warning: no trajectory_gnss written: {exc}", markup=False)
        return None, {"written": False, "reason": str(exc), "meaning": MEANING}
    off = gnss_offset(tr, fixes, model=model)
    track = gnss_frame_trajectory(tr, off)
    std = off.std_at(tr.times)
    covs = np.zeros((len(tr), 3, 3))
    covs[:, 0, 0] = covs[:, 1, 1] = std**2
    pc = getattr(result, "pose_covs", None)
    covs[:, 2, 2] = np.nan if pc is None else np.asarray(pc)[:, 2, 2]
    record = {
        "written": True,
        "meaning": MEANING,
        "model": model.to_dict(),
        "model_from": "autocorrelation of the fused fixes' residuals from trajectory.csv "
        "(stemmap.slam.gnss_track.fit_gnss_offset_model)",
        "estimate": "smoothed (Kalman filter + Rauch-Tung-Striebel over the whole run; offline)",
        "offset_rms_2d_m": round(float(np.sqrt(np.mean(np.sum(off.offset**2, axis=1)))), 4),
        "std_per_axis_m_median": round(float(np.median(std)), 4),
    }
    return GnssTrack(track, std, covs, record), record


def gnss_track_layers(track: GnssTrack) -> list[Any]:
    """GeoPackage layers ``trajectory_gnss`` (one LineString) and ``poses_gnss`` (Points:
    ``time_s``, ``theta``, ``std_m``) of the track."""
    from stemmap.io.geo import GeoLayer

    tr = track.trajectory
    t = np.asarray(tr.times, dtype=np.float64)
    return [
        GeoLayer(
            "trajectory_gnss",
            tr.xy,
            {"t_start_s": t[:1], "t_end_s": t[-1:], "n_poses": np.array([len(t)])},
            line=True,
        ),
        GeoLayer("poses_gnss", tr.xy, {"time_s": t, "theta": tr.poses[:, 2], "std_m": track.std}),
    ]


def write_gnss_track(
    out_dir: Path, track: GnssTrack, *, crs: str | None, frame: str, trajectory_format: str
) -> list[str]:
    """Write ``trajectory_gnss.csv`` (or ``.tum``) and, with ``crs``, ``trajectory_gnss.geojson``;
    return the file names written."""
    from stemmap.io.atomic import atomic_write
    from stemmap.io.geo import georeference_features
    from stemmap.io.trajectory import write_trajectory_csv, write_trajectory_tum

    tr = track.trajectory
    if trajectory_format == "tum":
        names = ["trajectory_gnss.tum"]
        write_trajectory_tum(out_dir / names[0], tr)
    else:
        names = ["trajectory_gnss.csv"]
        write_trajectory_csv(out_dir / names[0], tr, covs=track.covs)
    if crs is not None:
        feats = [
            {
                "type": "Feature",
                "properties": {"time_s": float(t), "theta": float(p[2]), "std_m": float(s)},
            }
            for t, p, s in zip(tr.times, tr.poses, track.std, strict=True)
        ]
        doc = georeference_features(
            {"type": "FeatureCollection", "features": feats}, tr.xy, crs, frame
        )
        doc["stemmap"]["meaning"] = MEANING
        names.append("trajectory_gnss.geojson")
        with atomic_write(out_dir / names[-1]) as fh:
            fh.write(json.dumps(doc, allow_nan=False, separators=(",", ":")) + "\n")
    return names
