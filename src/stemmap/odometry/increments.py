"""Loose coupling by relative motion: information-weighted fusion of pose-output odometries'
increments (visual-lidar §2.4).

The visual-lidar paper couples its visual and LiDAR odometry "loosely" in an EKF of their
outputs without giving the filter. :func:`stemmap.odometry.fusion.fuse_sources` takes a
scan-to-map lidar's poses as absolute measurements; but neither odometry measures where the
vehicle *is*, only how it moved: each one's pose error is the sum of its step errors (plus,
for a scan-to-map odometry, a jitter of each pose about that drifting path). Fusing the absolute
poses makes the filter believe the lidar's drift to its jitter level (docs/algorithms/
slam-frontends.md). Here each source is a chain of consecutive increments instead, with its
own error model, and the fused increment is their information-weighted mean:

* a source's increment ``D_s(i, j) = p_i⁻¹ ⊕ p_j`` (body frame of pose ``i``) has the
  first-order covariance of compounding its steps (Smith, Self & Cheeseman 1990, the
  compounding Jacobians of planar poses)::

      C(i, j+1) = F C(i, j) Fᵀ + G Σ_j Gᵀ,   F = [[1, 0, -r_y], [0, 1, r_x], [0, 0, 1]],
      G = diag(R(D_θ), 1),  r = R(D_θ) d_xy (the step's translation in frame i)

  with ``Σ_j`` the step's white covariance (a scan matcher's registration covariance, a VO's
  PnP-inlier noise), plus two terms the papers do not model (ours): a pose **jitter** ``J`` at
  both ends (a scan-to-map odometry's pose error about its drifting path: ``S J Sᵀ`` at the
  start, with ``S = ∂D/∂p_i``, and ``G J Gᵀ`` at the end) and a per-step **bias** ``b``
  common to all the steps of one increment (a VO's scale and heading-rate error:
  ``(Σ_k J_k) diag(b²) (Σ_k J_k)ᵀ``, ``J_k = ∂D/∂d_k``);
* the fused increment of the same span is ``D = (Σ_s C_s⁻¹)⁻¹ Σ_s C_s⁻¹ D_s`` (headings
  averaged as differences from the first source's). For independent, unbiased sources with
  the right covariances this is the minimum-variance linear combination: its error variance
  is at most the better source's, per span;
* the drive is cut into spans of ``span`` steps; every pose is the fused increment from its
  span's start, and each span starts at the previous span's fused end. ``span=None`` is one
  span (every pose fused from the first: the combination above holds for every pose, but
  a jitter of the start frame weighs on the whole drive).

A step a source did not measure (NaN covariance: a lost VO frame, a held lidar frame) makes
that source's increments over it unusable: the source drops out until the next span.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.errors import ConfigError, InputError
from stemmap.slam.motion import between, compose
from stemmap.types import FloatArray, Trajectory, wrap_angle

__all__ = ["IncrementSource", "fuse_increments"]


@dataclass(frozen=True, eq=False)
class IncrementSource:
    """A pose-output odometry and its error model, for :func:`fuse_increments`.

    Parameters
    ----------
    trajectory : Trajectory
        Poses (N) on the fusion's time base (resample with :meth:`Trajectory.interpolate`).
    step_cov : ndarray (N - 1, 3, 3) or (3, 3)
        White covariance of each step ``p_k⁻¹ ⊕ p_{k+1}`` (body frame of ``p_k``; m², rad²).
        A row with a NaN: the step was not measured.
    jitter : ndarray (3, 3), optional
        Covariance of each pose about the source's drifting path (body frame); default 0.
    bias : ndarray (3,), optional
        1-sigma of a per-step error (forward m, lateral m, heading rad) shared by all steps
        of an increment; default 0.
    name : str
    """

    trajectory: Trajectory
    step_cov: FloatArray
    jitter: FloatArray | None = None
    bias: FloatArray | None = None
    name: str = ""

    def __post_init__(self) -> None:
        n = len(self.trajectory)
        label = self.name or "increment source"
        if n < 2:
            raise InputError(f"{label}: need at least 2 poses.")
        c = np.asarray(self.step_cov, dtype=np.float64)
        if c.shape == (3, 3):
            c = np.broadcast_to(c, (n - 1, 3, 3))
        if c.shape != (n - 1, 3, 3):
            raise InputError(f"{label}: step_cov must be (3, 3) or ({n - 1}, 3, 3), got {c.shape}.")
        object.__setattr__(self, "step_cov", np.array(c))
        j = np.zeros((3, 3)) if self.jitter is None else np.asarray(self.jitter, np.float64)
        b = np.zeros(3) if self.bias is None else np.asarray(self.bias, np.float64).reshape(3)
        if (
            j.shape != (3, 3)
            or not np.all(np.isfinite(j))
            or np.any(np.linalg.eigvalsh(j) < -1e-15)
        ):
            raise ConfigError(f"{label}: jitter must be a finite PSD (3, 3) covariance.")
        if not np.all(np.isfinite(b)) or np.any(b < 0):
            raise ConfigError(f"{label}: bias must be finite and >= 0.")
        object.__setattr__(self, "jitter", j)
        object.__setattr__(self, "bias", b)


def _lever(v: FloatArray) -> FloatArray:
    """``∂(a ⊕ q)/∂a`` for an additive perturbation of ``a`` in its parent frame, ``v`` the
    vector from ``a`` to ``a ⊕ q`` in that frame."""
    return np.array([[1.0, 0.0, -v[1]], [0.0, 1.0, v[0]], [0.0, 0.0, 1.0]])


def _rot(th: float) -> FloatArray:
    c, s = math.cos(th), math.sin(th)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _span_covs(src: IncrementSource, i: int, j: int) -> tuple[FloatArray, FloatArray]:
    """Increments ``D(i, k)`` and their covariances for ``k = i+1 .. j`` (module docstring);
    covariances are NaN from the first unmeasured step on."""
    p = src.trajectory.poses
    D = between(p[i], p[i + 1 : j + 1])
    n = j - i
    out = np.full((n, 3, 3), np.nan)
    C = np.zeros((3, 3))
    Gsum = np.zeros((3, 3))  # ∂D/∂(common per-step error)
    Jit = src.jitter
    b2 = np.diag(np.asarray(src.bias) ** 2)
    assert Jit is not None
    prev = np.zeros(3)
    for k in range(n):
        Sk = src.step_cov[i + k]
        if not np.all(np.isfinite(Sk)):
            break
        G = _rot(prev[2])
        F = _lever(D[k, :2] - prev[:2])
        C = F @ C @ F.T + G @ Sk @ G.T
        Gsum = F @ Gsum + G
        S = _lever(D[k, :2])  # start-pose perturbation
        Ge = _rot(D[k, 2])
        out[k] = C + S @ Jit @ S.T + Ge @ Jit @ Ge.T + Gsum @ b2 @ Gsum.T
        prev = D[k]
    return D, out


def _span_end(measured: NDArray[np.bool_], i: int, j: int) -> int:
    """End of the span that starts at pose ``i`` (at most ``j``): the step before the set of
    sources that measured every step since ``i`` changes, so a source that lost a step drops
    out only until the span after it."""
    m = measured[:, i:j]
    # a source measures steps i..i+k iff its cumulative product is True there
    run = np.cumprod(m, axis=1).astype(bool)
    change = np.any(run != run[:, :1], axis=0)
    if not run[:, 0].all():  # a source out from the start: end where it measures again
        back = np.any(m & ~run[:, :1], axis=0)
        change |= back
    k = np.flatnonzero(change)
    return i + int(k[0]) if k.size else j


def fuse_increments(
    sources: Sequence[IncrementSource],
    *,
    span: int | None = None,
    initial_pose: ArrayLike | None = None,
) -> tuple[Trajectory, FloatArray]:
    """Fuse pose-output odometries by their increments (module docstring; visual-lidar §2.4
    loose coupling, the filter ours).

    Parameters
    ----------
    sources : sequence of IncrementSource
        Same time base (equal ``trajectory.times``).
    span : int >= 1 or None
        Steps per span (None: one span over the whole drive).
    initial_pose : (3,), optional
        The fused path's first pose; default the first source's first pose.

    Returns
    -------
    trajectory : Trajectory
    covariances : ndarray (N, 3, 3)
        Covariance of each fused pose relative to its span's start (zero at span starts).

    Raises
    ------
    InputError
        No source, or sources on different time bases.
    ConfigError
        ``span`` < 1.
    """
    srcs = list(sources)
    if not srcs:
        raise InputError("fuse_increments: no source given.")
    t = srcs[0].trajectory.times
    for s in srcs[1:]:
        if s.trajectory.times.shape != t.shape or not np.allclose(s.trajectory.times, t):
            raise InputError(
                f"fuse_increments: {s.name or 'a source'} is not on the first source's time "
                "base; resample it (Trajectory.interpolate)."
            )
    if span is not None and span < 1:
        raise ConfigError(f"fuse_increments: span must be >= 1 or None, got {span}.")
    n = t.shape[0]
    L = n - 1 if span is None else int(span)
    p0 = srcs[0].trajectory.poses[0] if initial_pose is None else initial_pose
    poses = np.empty((n, 3))
    poses[0] = np.asarray(p0, dtype=np.float64).reshape(3)
    covs = np.zeros((n, 3, 3))
    measured = np.stack([np.all(np.isfinite(s.step_cov), axis=(1, 2)) for s in srcs])
    i = 0
    while i < n - 1:
        j = _span_end(measured, i, min(i + L, n - 1))
        parts = [_span_covs(s, i, j) for s in srcs]
        ref = parts[0][0]
        info = np.zeros((j - i, 3, 3))
        vec = np.zeros((j - i, 3))
        for D, C in parts:
            ok = np.isfinite(C[:, 0, 0])
            Dr = D.copy()
            Dr[:, 2] = ref[:, 2] + wrap_angle(D[:, 2] - ref[:, 2])
            W = np.zeros_like(C)
            W[ok] = np.linalg.inv(C[ok])
            info += W
            vec += np.einsum("nij,nj->ni", W, Dr)
        have = np.abs(np.linalg.det(info)) > 0
        fused = ref.copy()  # no source measured these steps: the first source's increments
        cf = np.full((j - i, 3, 3), np.nan)
        cf[have] = np.linalg.inv(info[have])
        fused[have] = np.einsum("nij,nj->ni", cf[have], vec[have])
        poses[i + 1 : j + 1] = compose(poses[i], fused)
        covs[i + 1 : j + 1] = cf
        i = j
    poses[:, 2] = wrap_angle(poses[:, 2])
    return Trajectory(t, poses, frame=srcs[0].trajectory.frame), covs
