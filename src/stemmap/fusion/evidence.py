"""Dempster-Shafer evidence on the frame of discernment Omega = {T, NT} (trunk / not trunk).

A mass function (basic probability assignment, BPA) on this frame has three focal elements:
``{T}``, ``{NT}`` and ``Omega = {T, NT}`` (ignorance). :class:`Mass` holds a *batch* of them as
three arrays of equal shape, so a whole frame's regions combine in one vectorised call.

References
----------
Xue J., Fan B., Yan J., Dong S., Ding Q. (2018). Trunk detection based on laser radar and vision
data fusion. Int J Agric & Biol Eng 11(6): 20-26. §2.4.1 (BPA), eq. 16 (Dempster's rule), eq. 17
(decision rule).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.errors import ConfigError, InputError
from stemmap.types import FloatArray

__all__ = [
    "XUE2018_DECISION",
    "Combination",
    "Mass",
    "combine_dempster",
    "decide_xue2018",
]

#: Decision thresholds of Xue et al. (2018) §3.2.4: epsilon_1 = epsilon_2 = 0.1.
XUE2018_DECISION: dict[str, float] = {"eps1": 0.1, "eps2": 0.1}

_TOL = 1e-9


@dataclass(frozen=True, eq=False)
class Mass:
    """A batch of mass functions on {T, NT} with ignorance Omega.

    Parameters
    ----------
    t, nt, theta : array_like, same shape (scalars allowed)
        Masses of {T}, {NT} and Omega = {T, NT}; each in [0, 1], summing to 1 per element.

    Raises
    ------
    InputError
        If a mass is outside [0, 1], not finite, the shapes differ, or a sum differs from 1 by
        more than 1e-9.

    Examples
    --------
    >>> m = Mass(0.9, 0.1, 0.0)
    >>> float(m.t), m.shape
    (0.9, ())
    >>> Mass(0.9, 0.3, 0.0)  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    stemmap.errors.InputError: mass functions must sum to 1; element 0 sums to 1.2 ...
    """

    t: FloatArray
    nt: FloatArray
    theta: FloatArray

    def __post_init__(self) -> None:
        arrs = []
        for name in ("t", "nt", "theta"):
            a = np.array(getattr(self, name), dtype=np.float64, copy=True)
            arrs.append(a)
        t, nt, th = arrs
        if not (t.shape == nt.shape == th.shape):
            raise InputError(
                f"mass arrays must share one shape, got t{t.shape}, nt{nt.shape}, theta{th.shape}."
            )
        stack = np.stack([t, nt, th])
        if not np.all(np.isfinite(stack)):
            raise InputError("masses must be finite numbers; got NaN or inf.")
        bad = (stack < -_TOL) | (stack > 1 + _TOL)
        if np.any(bad):
            raise InputError(f"every mass must lie in [0, 1]; got {float(stack[bad].flat[0]):.6g}.")
        s = stack.sum(axis=0)
        off = np.abs(s - 1.0) > 1e-9
        if np.any(off):
            k = int(np.flatnonzero(off.reshape(-1))[0])
            raise InputError(
                f"mass functions must sum to 1; element {k} sums to {s.reshape(-1)[k]:.6g} "
                f"(t={t.reshape(-1)[k]:.6g}, nt={nt.reshape(-1)[k]:.6g}, "
                f"theta={th.reshape(-1)[k]:.6g})."
            )
        for name, a in zip(("t", "nt", "theta"), (t, nt, th), strict=True):
            a = np.clip(a, 0.0, 1.0)
            a.setflags(write=False)
            object.__setattr__(self, name, a)

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(self.t.shape)

    def __len__(self) -> int:
        return int(self.t.size)

    @property
    def belief_t(self) -> FloatArray:
        """Bel({T}) = m(T)."""
        return self.t

    @property
    def plausibility_t(self) -> FloatArray:
        """Pl({T}) = m(T) + m(Omega)."""
        return self.t + self.theta

    def pignistic_t(self) -> FloatArray:
        """Pignistic probability of T: m(T) + m(Omega) / 2 (Smets)."""
        return self.t + 0.5 * self.theta

    @classmethod
    def vacuous(cls, shape: int | tuple[int, ...] = ()) -> Mass:
        """Total ignorance: m(Omega) = 1."""
        z = np.zeros(shape)
        return cls(z, z, np.ones(shape))

    @classmethod
    def from_t_nt(cls, t: ArrayLike, nt: ArrayLike) -> Mass:
        """Build from m(T) and m(NT); m(Omega) = 1 - m(T) - m(NT)."""
        ta = np.asarray(t, dtype=np.float64)
        na = np.asarray(nt, dtype=np.float64)
        return cls(ta, na, 1.0 - ta - na)

    def __getitem__(self, idx: int | slice | NDArray[np.bool_] | NDArray[np.int64]) -> Mass:
        return Mass(self.t[idx], self.nt[idx], self.theta[idx])

    def as_array(self) -> FloatArray:
        """Stacked masses, shape (..., 3) as (m(T), m(NT), m(Omega))."""
        return np.stack([self.t, self.nt, self.theta], axis=-1)


@dataclass(frozen=True, eq=False)
class Combination:
    """Result of Dempster's rule on a batch.

    Attributes
    ----------
    mass : Mass
        Combined masses; where the evidence is in total conflict (K = 1) the combination is
        undefined and those elements hold the vacuous mass (m(Omega) = 1) with ``ok`` False.
    conflict : ndarray
        K of eq. 16, in [0, 1].
    ok : ndarray of bool
        False where K = 1 (total conflict).
    """

    mass: Mass
    conflict: FloatArray
    ok: NDArray[np.bool_]

    def __bool__(self) -> bool:
        return bool(np.all(self.ok))

    @property
    def reason(self) -> str:
        n = int(np.size(self.ok) - np.count_nonzero(self.ok))
        return "" if n == 0 else f"{n} element(s) in total conflict (K = 1); combination undefined"


def combine_dempster(m1: Mass, m2: Mass) -> Combination:
    """Dempster's rule of combination on {T, NT} (Xue et al. 2018, eq. 16).

    m(Z) = sum_{X ∩ Y = Z} m1(X) m2(Y) / (1 - K),  K = sum_{X ∩ Y = ∅} m1(X) m2(Y).

    On this frame the only empty intersection is {T} ∩ {NT}, so
    K = m1(T) m2(NT) + m1(NT) m2(T).

    Parameters
    ----------
    m1, m2 : Mass
        Batches of the same shape (or broadcastable: a scalar mass combines with a batch).

    Returns
    -------
    Combination
        Combined masses and conflict K. Falsy where K = 1 (then the rule is undefined).

    Examples
    --------
    Xue et al. (2018) Table 3, region 1 (laser D with vision region 1):

    >>> c = combine_dempster(Mass(0.9, 0.1, 0.0), Mass(0.576, 0.324, 0.1))
    >>> round(float(c.mass.t), 3), round(float(c.mass.nt), 3), round(float(c.conflict), 4)
    (0.935, 0.065, 0.3492)
    >>> bool(combine_dempster(Mass(1.0, 0.0, 0.0), Mass(0.0, 1.0, 0.0)))
    False
    """
    t1, n1, o1 = np.broadcast_arrays(m1.t, m1.nt, m1.theta)
    t2, n2, o2 = np.broadcast_arrays(m2.t, m2.nt, m2.theta)
    try:
        t1, t2 = np.broadcast_arrays(t1, t2)
        n1, n2 = np.broadcast_arrays(n1, n2)
        o1, o2 = np.broadcast_arrays(o1, o2)
    except ValueError as exc:
        raise InputError(f"mass batches of shapes {m1.shape} and {m2.shape} differ.") from exc
    k = t1 * n2 + n1 * t2
    t = t1 * t2 + t1 * o2 + o1 * t2
    nt = n1 * n2 + n1 * o2 + o1 * n2
    th = o1 * o2
    denom = 1.0 - k
    ok = denom > 1e-12
    safe = np.where(ok, denom, 1.0)
    t = np.where(ok, t / safe, 0.0)
    nt = np.where(ok, nt / safe, 0.0)
    th = np.where(ok, th / safe, 1.0)
    # Renormalise against rounding so the Mass invariant (sum 1) holds to 1e-12.
    s = t + nt + th
    return Combination(Mass(t / s, nt / s, th / s), np.asarray(k, dtype=np.float64), ok)


def decide_xue2018(m: Mass, *, eps1: float = 0.1, eps2: float = 0.1) -> NDArray[np.bool_]:
    """Decision rule of Xue et al. (2018), eq. 17: the target is a trunk iff

    m(T) - m(NT) > eps1,  m(Omega) < eps2,  m(T) > m(Omega).

    Parameters
    ----------
    m : Mass
        Combined masses (batch).
    eps1, eps2 : float
        Thresholds; the paper uses 0.1 for both (:data:`XUE2018_DECISION`).

    Returns
    -------
    ndarray of bool, shape ``m.shape``

    Examples
    --------
    >>> bool(decide_xue2018(Mass(0.935, 0.065, 0.0)))
    True
    >>> bool(decide_xue2018(Mass(0.0, 1.0, 0.0)))
    False
    """
    if not (0.0 <= eps1 < 1.0 and 0.0 < eps2 <= 1.0):
        raise ConfigError(
            f"decision thresholds must be eps1 in [0, 1), eps2 in (0, 1]; got {eps1}, {eps2}."
        )
    return np.asarray((m.t - m.nt > eps1) & (m.theta < eps2) & (m.t > m.theta))
