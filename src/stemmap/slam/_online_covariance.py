"""Pose covariance of the online mapper, carried scan by scan and across re-anchors (ours).

Issue 14 (:attr:`stemmap.slam.online.OnlineMapper.pose_covs`, ``trajectory.csv`` of
``stemmap map --realtime``): at every iSAM2 update the latest keyframe's marginal
(``ISAM2.marginalCovariance``: the newest key sits at the Bayes tree's root, Kaess et al. 2012,
so the recovery touches few cliques; with the carrying +0.04 ms CPU per scan at the median,
+0.17 ms at p99, ~1.1x: ``benchmarks/slam_field.py --parts online --worker online`` on VP,
before / after alternated twice) is carried scan by scan with the dead-reckoned sensor
increments' covariance (``C <- Ad(d⁻¹) C Ad(d⁻¹)ᵀ + Q``, the propagation of
:func:`~stemmap.slam._graph_odometry.frame_covariances`): O(1) per scan. A re-anchor's prior is
the marginal with its sigmas capped; the part the cap leaves out (the PSD part of the
difference) is carried from the anchor on the next window's marginals, so the covariance does
not reset. The tracker's per-scan corrections between updates are not in it (conservative
there). The reported covariance is ``pose_cov_factor`` (8.6, chosen on Victoria Park's first
half against the GPS) times this: without the batch's odometry self-calibration the odometry's
bias is outside the model (docs/outputs.md, "Pose covariance columns").
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

import numpy as np

from stemmap.slam._graph_odometry import frame_covariances
from stemmap.slam._graph_revisits import _adjoint_inv
from stemmap.slam._grow import _Grow
from stemmap.slam.motion import between
from stemmap.types import FloatArray

log = logging.getLogger(__name__)


class PoseCovarianceCarry:
    """The current scan's sensor-pose covariance (GTSAM tangent, map frame) and its history.

    Parameters
    ----------
    prior_sigmas : (σx, σy, σθ), m, m, rad, the first pose's prior (the covariance before the
        first iSAM2 update)
    """

    def __init__(self, prior_sigmas: Sequence[float]) -> None:
        self.C = np.diag(np.array(prior_sigmas) ** 2)
        # what a re-anchor's capped prior left out (tangent at the anchor) and the anchor pose
        self.C_out = np.zeros((3, 3))
        self.anchor = np.zeros(3)
        self._Cs = _Grow((3, 3))  # self.C at every scan
        self._th = _Grow(())  # reported vehicle heading at every scan

    def carry(self, sp_prev: FloatArray, sp_now: FloatArray, q: FloatArray) -> None:
        """Carry ``C`` over one scan's sensor increment ``sp_prev -> sp_now`` of covariance
        ``q``: ``C <- Ad(d⁻¹) C Ad(d⁻¹)ᵀ + q`` (module docs)."""
        A = _adjoint_inv(between(sp_prev, sp_now))
        self.C = A @ self.C @ A.T + q

    def record(self, heading: float) -> None:
        """Keep ``C`` and the reported vehicle heading (rad) of the scan just tracked."""
        self._Cs.append(self.C)
        self._th.append(heading)

    def update(self, isam: Any, key: int, p: Any) -> None:
        """Set ``C`` to the map-frame covariance of the keyframe sensor pose ``p`` (``key``):
        iSAM2's marginal (Kaess et al. 2012, iSAM2, Alg. 7: the latest key sits near the Bayes
        tree's root, so recovering it touches few cliques) plus what the re-anchors' capped
        priors left out, carried from the anchor (``Ad(rel⁻¹) C Ad(rel⁻¹)ᵀ``)."""
        try:
            cov = np.asarray(isam.marginalCovariance(key), dtype=np.float64)
        except RuntimeError as exc:  # an indeterminate system: keep the dead-reckoned one
            log.warning("online: pose marginal unavailable (%s)", exc)
            return
        if self.C_out.any():
            A = _adjoint_inv(between(self.anchor, np.array([p.x(), p.y(), p.theta()])))
            cov = cov + A @ self.C_out @ A.T
        self.C = np.asarray(0.5 * (cov + cov.T), dtype=np.float64)

    def reanchor(self, isam: Any, key: int, pk: Any, cap_sigmas: Sequence[float]) -> FloatArray:
        """The prior of a new smoother anchored at keyframe pose ``pk`` (``key``): its marginal,
        the sigmas capped at ``cap_sigmas`` (m, m, rad), the correlations kept. After a stretch
        without trees (a transit) the absolute uncertainty reaches tens of metres, and a prior
        that weak only sets the gauge while GTSAM rejects the ill-conditioned system (as for a
        weak first-pose prior, see graph.py / GNSS). The part of ``C`` (this window's marginal
        + what earlier caps left out) the capped prior leaves out (its PSD part) is kept to be
        carried on the new window's poses by :meth:`update`, so the covariance does not
        reset."""
        cov_k = np.asarray(isam.marginalCovariance(key), dtype=np.float64)
        sd = np.sqrt(np.maximum(np.diag(cov_k), 1e-20))
        scale = np.minimum(1.0, np.asarray(cap_sigmas) / sd)
        cov_k = cov_k * np.outer(scale, scale)
        w, V = np.linalg.eigh(self.C - cov_k)
        self.C_out = (V * np.maximum(w, 0.0)) @ V.T
        self.anchor = np.array([pk.x(), pk.y(), pk.theta()])
        return cov_k

    def pose_covs(self, factor: float, offset: tuple[float, float]) -> FloatArray:
        """(N, 3, 3) covariance of the vehicle pose of every recorded scan (x, y, θ, map frame):
        each scan's sensor-pose covariance carried through the mounting ``offset`` (m) and
        rotated, as :func:`~stemmap.slam._graph_odometry.frame_covariances` does with every
        frame its own anchor, times ``factor``."""
        n = self._Cs.n
        fr = np.arange(n)
        return factor * frame_covariances(
            self._Cs.a[:n], fr, fr, np.zeros((n, 3)), np.zeros((n, 3, 3)), offset,
            self._th.a[:n],
        )  # fmt: skip
