"""Live viewer: a Rerun recording (``.rrd``) of an online mapping run (``stemmap map --rerun``).

:class:`RerunRecorder` is called after every scan of :class:`stemmap.slam.online.OnlineMapper`
(``replay(..., on_scan=recorder)``) and logs, on the timelines ``time`` (s, sensor clock) and
``scan`` (index), so a user can scrub through the run in the Rerun viewer
(``rerun FILE.rrd``):

* ``world/vehicle``: the current vehicle position; ``world/detections``: this scan's trunk
  detections placed with the current pose (radius = half the measured diameter);
* every ``map_every`` scans: ``world/path`` (the causal path so far), ``world/trees`` (trunks,
  radius = half the diameter) and ``world/trees/uncertainty`` (the 2-sigma ellipse of each tree
  whose covariance is known, a 24-point polygon: Rerun's ``Ellipses2D`` has no rotation).

rerun-sdk is an optional dependency (``pip install 'stemmap[viewer]'``).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from stemmap.errors import ConfigError
from stemmap.types import FloatArray, StemMap

__all__ = ["RerunRecorder", "sigma_ellipses"]

_CIRCLE = np.column_stack(
    (np.cos(np.linspace(0, 2 * math.pi, 25)), np.sin(np.linspace(0, 2 * math.pi, 25)))
)


def sigma_ellipses(xy: FloatArray, covs: FloatArray, k: float = 2.0) -> FloatArray:
    """(N, 25, 2) closed polygons of the ``k``-sigma ellipses of 2x2 covariances ``covs`` at
    ``xy``: ``x + k L u`` with ``L`` the Cholesky factor and ``u`` on the unit circle."""
    c = np.asarray(covs, dtype=np.float64).reshape(-1, 2, 2)
    jitter = np.eye(2)[None] * 1e-12
    low = np.linalg.cholesky(c + jitter)
    return np.asarray(xy).reshape(-1, 1, 2) + k * np.einsum("nij,pj->npi", low, _CIRCLE)


class RerunRecorder:
    """Per-scan logger into ``path`` (``.rrd``); use as ``on_scan`` of ``replay``."""

    def __init__(self, path: str | Path, *, map_every: int = 50) -> None:
        try:
            import rerun as rr
        except ImportError as exc:  # pragma: no cover - depends on the environment
            raise ConfigError(
                "--rerun needs the optional rerun-sdk package: pip install 'stemmap[viewer]' "
                "(or pip install rerun-sdk)."
            ) from exc
        if map_every < 1:
            raise ConfigError(f"map_every must be >= 1, got {map_every}.")
        self.rr = rr
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.rec = rr.RecordingStream("stemmap")
        self.rec.save(str(self.path))
        self.map_every = map_every
        self.path_xy: list[tuple[float, float]] = []
        self.n_logged = 0

    def __call__(self, mapper: Any, f: int) -> None:
        rr, rec = self.rr, self.rec
        t = float(mapper.times.a[f])
        rec.set_time("time", duration=t)
        rec.set_time("scan", sequence=int(f))
        x, y, th = mapper.pose
        self.path_xy.append((x, y))
        rec.log("world/vehicle", rr.Points2D([[x, y]], radii=0.6, colors=[[230, 60, 60]]))
        i0, i1 = int(mapper.ptr.a[f]), int(mapper.ptr.a[f + 1])
        r, b = mapper.rng.a[i0:i1], mapper.brg.a[i0:i1]
        d = mapper.dia.a[i0:i1]
        a_, b_ = mapper.offset
        sx = x + math.cos(th) * a_ - math.sin(th) * b_
        sy = y + math.sin(th) * a_ + math.cos(th) * b_
        det = np.column_stack((sx + r * np.cos(th + b), sy + r * np.sin(th + b)))
        rad = np.where(np.isfinite(d), 0.5 * d, 0.15)
        rec.log("world/detections", rr.Points2D(det, radii=rad, colors=[[250, 200, 40]]))
        if f % self.map_every == 0:
            self.log_map(mapper.stem_map(with_covariance=True))
        self.n_logged += 1

    def log_map(self, stem_map: StemMap) -> None:
        """Path so far, trunks and their 2-sigma ellipses (at the current time)."""
        rr, rec = self.rr, self.rec
        if len(self.path_xy) > 1:
            rec.log("world/path", rr.LineStrips2D([self.path_xy], colors=[[60, 120, 230]]))
        if len(stem_map) == 0:
            return
        xy = stem_map.xy
        d = np.array([t.diameter for t in stem_map])
        rec.log(
            "world/trees",
            rr.Points2D(xy, radii=np.where(np.isfinite(d), 0.5 * d, 0.15), colors=[[40, 160, 60]]),
        )
        covs = np.array([t.cov for t in stem_map])
        ok = np.isfinite(covs).all(axis=(1, 2)) & (np.linalg.det(np.nan_to_num(covs)) > 0)
        if ok.any():
            polys = sigma_ellipses(xy[ok], covs[ok])
            rec.log("world/trees/uncertainty", rr.LineStrips2D(list(polys), colors=[[40, 160, 60]]))

    def close(self) -> None:
        """Flush and close the recording file."""
        self.rec.flush()
        self.rec.disconnect()
