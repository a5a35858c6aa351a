"""Crane kinematics: homogeneous transforms, Denavit-Hartenberg chains, forward and inverse.

Zheng et al. 2012 §5 puts the laser scanner and an AHRS on the crane's outer boom and composes
the trunk pose relative to the harvesting head from homogeneous 4x4 matrices (eq. 11),
``T_H^T = T_S^T * T_H^S``, where the scanner-to-head transform comes from the crane's D-H
parameters and joint encoders. This module provides those pieces:

* generic transforms and a standard-D-H chain with forward kinematics and a damped-least-squares
  numerical inverse for any crane (:class:`DHChain`);
* :class:`ForestryCrane`, the usual harvester crane -- slewing column, boom, stick, telescope and a
  rotator carrying a freely hanging head -- with a closed-form, vectorised inverse used by the
  planner (hundreds of set-points in microseconds, well inside the paper's 10 ms control period).

Frames: the crane base frame has z up and x forward along the machine; metres and radians.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.errors import ConfigError, StemmapError

__all__ = [
    "DHChain",
    "DHJoint",
    "ForestryCrane",
    "UnreachableError",
    "dh_transform",
    "invert_transform",
    "make_transform",
    "rot_z",
]

FloatArray = NDArray[np.float64]


class UnreachableError(StemmapError):
    """A target pose lies outside the crane's workspace or joint limits."""


def rot_z(angle: float) -> FloatArray:
    """3x3 rotation about z by ``angle`` (rad)."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def make_transform(
    rotation: ArrayLike | None = None, translation: ArrayLike = (0, 0, 0)
) -> FloatArray:
    """Homogeneous 4x4 transform from a 3x3 rotation (default identity) and a translation."""
    T = np.eye(4)
    if rotation is not None:
        T[:3, :3] = np.asarray(rotation, dtype=np.float64)
    T[:3, 3] = np.asarray(translation, dtype=np.float64)
    return T


def invert_transform(T: ArrayLike) -> FloatArray:
    """Inverse of a rigid 4x4 transform (``R^T``, ``-R^T t``), exact and cheaper than inv()."""
    M = np.asarray(T, dtype=np.float64)
    R, t = M[:3, :3], M[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def dh_transform(theta: ArrayLike, d: ArrayLike, a: ArrayLike, alpha: ArrayLike) -> FloatArray:
    """Standard Denavit-Hartenberg link transform ``Rz(theta) Tz(d) Tx(a) Rx(alpha)``.

    Broadcasts over its arguments: scalars give (4, 4), arrays of shape (K,) give (K, 4, 4).
    """
    th, d_, a_, al = np.broadcast_arrays(
        *(np.asarray(v, dtype=np.float64) for v in (theta, d, a, alpha))
    )
    ct, st, ca, sa = np.cos(th), np.sin(th), np.cos(al), np.sin(al)
    T = np.zeros((*th.shape, 4, 4))
    T[..., 0, 0] = ct
    T[..., 0, 1] = -st * ca
    T[..., 0, 2] = st * sa
    T[..., 0, 3] = a_ * ct
    T[..., 1, 0] = st
    T[..., 1, 1] = ct * ca
    T[..., 1, 2] = -ct * sa
    T[..., 1, 3] = a_ * st
    T[..., 2, 1] = sa
    T[..., 2, 2] = ca
    T[..., 2, 3] = d_
    T[..., 3, 3] = 1.0
    return T


@dataclass(frozen=True)
class DHJoint:
    """One joint of a standard-D-H chain.

    For a revolute joint the variable is ``theta`` (``theta = q + offset``); for a prismatic joint
    it is ``d`` (``d = q + offset``). Limits apply to ``q``; velocity and acceleration limits are
    per second (rad or m).
    """

    kind: Literal["revolute", "prismatic"]
    d: float = 0.0
    a: float = 0.0
    alpha: float = 0.0
    theta: float = 0.0
    offset: float = 0.0
    lower: float = -math.inf
    upper: float = math.inf
    max_velocity: float = math.inf
    max_acceleration: float = math.inf
    name: str = ""

    def __post_init__(self) -> None:
        if self.kind not in ("revolute", "prismatic"):
            raise ConfigError(f"joint kind must be 'revolute' or 'prismatic', got {self.kind!r}.")
        if not self.lower <= self.upper:
            raise ConfigError(
                f"joint {self.name!r}: lower limit {self.lower} > upper {self.upper}."
            )

    def transform(self, q: ArrayLike) -> FloatArray:
        if self.kind == "revolute":
            return dh_transform(np.asarray(q) + self.offset, self.d, self.a, self.alpha)
        return dh_transform(self.theta, np.asarray(q) + self.offset, self.a, self.alpha)


@dataclass(frozen=True)
class DHChain:
    """A serial chain of D-H joints between a base transform and a tool transform."""

    joints: tuple[DHJoint, ...]
    base: FloatArray = field(default_factory=lambda: np.eye(4))
    tool: FloatArray = field(default_factory=lambda: np.eye(4))

    @property
    def n_joints(self) -> int:
        return len(self.joints)

    @property
    def lower(self) -> FloatArray:
        return np.array([j.lower for j in self.joints])

    @property
    def upper(self) -> FloatArray:
        return np.array([j.upper for j in self.joints])

    def _check_q(self, q: ArrayLike) -> FloatArray:
        qa = np.asarray(q, dtype=np.float64)
        if qa.shape[-1:] != (self.n_joints,):
            raise ConfigError(f"expected {self.n_joints} joint values, got shape {qa.shape}.")
        return qa

    def frames(self, q: ArrayLike) -> FloatArray:
        """Base-frame poses of every joint frame: shape (n_joints + 1, 4, 4), frame 0 = base."""
        qa = self._check_q(q)
        out = np.empty((self.n_joints + 1, 4, 4))
        T = np.asarray(self.base, dtype=np.float64)
        out[0] = T
        for i, (j, qi) in enumerate(zip(self.joints, qa, strict=True)):
            T = T @ j.transform(qi)
            out[i + 1] = T
        return out

    def forward(self, q: ArrayLike) -> FloatArray:
        """Tool pose (4, 4) in the base frame; ``q`` of shape (n,) or (K, n) -> (K, 4, 4)."""
        qa = self._check_q(q)
        if qa.ndim == 2:
            T = np.broadcast_to(self.base, (qa.shape[0], 4, 4)).copy()
            for i, j in enumerate(self.joints):
                T = T @ j.transform(qa[:, i])
            return T @ self.tool
        return self.frames(qa)[-1] @ self.tool

    def within_limits(self, q: ArrayLike, tol: float = 1e-9) -> bool:
        qa = self._check_q(q)
        return bool(np.all(qa >= self.lower - tol) and np.all(qa <= self.upper + tol))

    def inverse_position(
        self,
        target: ArrayLike,
        q0: ArrayLike,
        *,
        tol: float = 1e-6,
        max_iter: int = 200,
        damping: float = 1e-2,
    ) -> FloatArray:
        """Numerical inverse for the tool *position*: damped least squares, clamped to limits.

        Parameters
        ----------
        target : (3,) tool position in the base frame, metres
        q0 : (n,) initial joint values
        tol : position tolerance, metres

        Raises
        ------
        UnreachableError
            When the iteration ends farther than ``tol`` from the target (outside the workspace
            or blocked by a joint limit); the message gives the remaining distance.
        """
        p_star = np.asarray(target, dtype=np.float64).reshape(3)
        q = np.clip(self._check_q(q0).astype(np.float64).copy(), self.lower, self.upper)
        eps = 1e-6
        err = np.inf
        for _ in range(max_iter):
            p = self.forward(q)[:3, 3]
            e = p_star - p
            err = float(np.linalg.norm(e))
            if err < tol:
                return q
            J = np.empty((3, self.n_joints))
            for i in range(self.n_joints):
                dq = np.zeros(self.n_joints)
                dq[i] = eps
                J[:, i] = (self.forward(q + dq)[:3, 3] - p) / eps
            lam2 = damping**2
            step = J.T @ np.linalg.solve(J @ J.T + lam2 * np.eye(3), e)
            q = np.clip(q + step, self.lower, self.upper)
        raise UnreachableError(
            f"target {np.round(p_star, 3).tolist()} is not reachable: the closest the chain gets "
            f"within its joint limits is {err:.3f} m away."
        )


# --------------------------------------------------------------------------------------------
# The standard forestry crane
# --------------------------------------------------------------------------------------------

#: Joint order of :class:`ForestryCrane` configurations.
CRANE_JOINTS = ("slew", "boom", "stick", "telescope", "rotator")


@dataclass(frozen=True)
class ForestryCrane:
    """A harvester crane: slewing column, boom, stick with telescope, rotator, hanging head.

    Geometry (metres): the slew axis is the base z axis; the boom pivot is ``column_height`` above
    the base origin and ``pivot_offset`` out along the slew direction; boom length ``boom``; stick
    length ``stick`` plus telescope extension ``q[3]``; the head hangs ``head_drop`` below the
    stick tip (it swings freely, so it stays vertical) and turns with the rotator.

    Configuration ``q = (slew, boom, stick, telescope, rotator)``: slew angle about z; boom
    elevation above horizontal; stick angle relative to the boom (negative folds it down);
    telescope extension (m); rotator yaw of the head relative to the slew direction.

    The same crane is available as a standard-D-H :meth:`chain` (to the stick tip), used for the
    scanner mount and to cross-check the closed-form inverse.
    """

    column_height: float = 2.2
    pivot_offset: float = 0.3
    boom: float = 4.6
    stick: float = 3.6
    head_drop: float = 0.9
    lower: tuple[float, ...] = (-2.4, math.radians(-25), math.radians(-165), 0.0, -math.pi)
    upper: tuple[float, ...] = (2.4, math.radians(80), math.radians(-15), 2.2, math.pi)
    max_velocity: tuple[float, ...] = (0.5, 0.3, 0.4, 0.5, 1.5)
    max_acceleration: tuple[float, ...] = (1.0, 0.6, 0.8, 1.0, 3.0)
    #: keep the boom-stick pair this fraction short of a straight line (elbow margin)
    stretch_margin: float = 0.95

    def __post_init__(self) -> None:
        for name in ("lower", "upper", "max_velocity", "max_acceleration"):
            if len(getattr(self, name)) != 5:
                raise ConfigError(
                    f"ForestryCrane.{name} needs 5 values ({', '.join(CRANE_JOINTS)})."
                )
        if np.any(np.asarray(self.lower) > np.asarray(self.upper)):
            raise ConfigError("ForestryCrane: every lower joint limit must be <= its upper limit.")

    # -- D-H model ------------------------------------------------------------------------------

    def chain(self) -> DHChain:
        """Standard-D-H chain base -> stick tip over (slew, boom, stick, telescope).

        Link 1 turns about the vertical slew axis and tilts z into the horizontal boom axis;
        link 2 is the boom; link 3 turns z along the stick (theta offset +90 deg); link 4 is the
        prismatic stick + telescope along that z axis.
        """
        lo, hi, v, a = self.lower, self.upper, self.max_velocity, self.max_acceleration
        joints = (
            DHJoint("revolute", d=self.column_height, a=self.pivot_offset, alpha=math.pi / 2,
                    lower=lo[0], upper=hi[0], max_velocity=v[0], max_acceleration=a[0],
                    name="slew"),
            DHJoint("revolute", a=self.boom, lower=lo[1], upper=hi[1], max_velocity=v[1],
                    max_acceleration=a[1], name="boom"),
            DHJoint("revolute", alpha=math.pi / 2, offset=math.pi / 2, lower=lo[2], upper=hi[2],
                    max_velocity=v[2], max_acceleration=a[2], name="stick"),
            DHJoint("prismatic", offset=self.stick, lower=lo[3], upper=hi[3],
                    max_velocity=v[3], max_acceleration=a[3], name="telescope"),
        )  # fmt: skip
        return DHChain(joints)

    # -- forward ---------------------------------------------------------------------------------

    def tip_position(self, q: ArrayLike) -> FloatArray:
        """Stick-tip position(s) in the base frame; ``q`` (5,) -> (3,), (K, 5) -> (K, 3)."""
        qa = np.asarray(q, dtype=np.float64)
        slew, boom, stick, tele = qa[..., 0], qa[..., 1], qa[..., 2], qa[..., 3]
        L2 = self.stick + tele
        r = self.pivot_offset + self.boom * np.cos(boom) + L2 * np.cos(boom + stick)
        z = self.column_height + self.boom * np.sin(boom) + L2 * np.sin(boom + stick)
        return np.stack((r * np.cos(slew), r * np.sin(slew), z), axis=-1)

    def head_pose(self, q: ArrayLike) -> FloatArray:
        """Harvesting-head pose(s) T_B^H as 4x4 (level, yaw = slew + rotator)."""
        qa = np.asarray(q, dtype=np.float64)
        tip = self.tip_position(qa)
        yaw = qa[..., 0] + qa[..., 4]
        c, s = np.cos(yaw), np.sin(yaw)
        T = np.zeros((*qa.shape[:-1], 4, 4))
        T[..., 0, 0], T[..., 0, 1] = c, -s
        T[..., 1, 0], T[..., 1, 1] = s, c
        T[..., 2, 2] = 1.0
        T[..., 3, 3] = 1.0
        T[..., :3, 3] = tip
        T[..., 2, 3] -= self.head_drop
        return T

    def stick_point(self, q: ArrayLike, along: float) -> FloatArray:
        """Point ``along`` metres out along the stick from the boom-stick joint, base frame."""
        qa = np.asarray(q, dtype=np.float64)
        slew, boom, stick = qa[..., 0], qa[..., 1], qa[..., 2]
        r = self.pivot_offset + self.boom * np.cos(boom) + along * np.cos(boom + stick)
        z = self.column_height + self.boom * np.sin(boom) + along * np.sin(boom + stick)
        return np.stack((r * np.cos(slew), r * np.sin(slew), z), axis=-1)

    # -- inverse ---------------------------------------------------------------------------------

    def inverse(self, head_xyz: ArrayLike, head_yaw: ArrayLike | None = None) -> FloatArray:
        """Closed-form inverse kinematics for head position(s) and yaw(s).

        The crane has five joints for four task coordinates (x, y, z, yaw); the redundancy is
        resolved by using the least telescope extension that keeps the boom-stick pair at most
        ``stretch_margin`` of full stretch, which keeps the elbow away from its singularity and
        the joint path smooth. The elbow folds down (stick angle negative), as on real cranes.

        Parameters
        ----------
        head_xyz : (3,) or (K, 3), base frame, metres
        head_yaw : scalar or (K,), rad, world yaw of the head (default: facing outwards)

        Returns
        -------
        q : (5,) or (K, 5)

        Raises
        ------
        UnreachableError
            Naming the first target and the joint limit or reach it violates.
        """
        p = np.asarray(head_xyz, dtype=np.float64)
        single = p.ndim == 1
        P = p.reshape(-1, 3)
        slew = np.arctan2(P[:, 1], P[:, 0])
        r = np.hypot(P[:, 0], P[:, 1]) - self.pivot_offset
        zz = P[:, 2] + self.head_drop - self.column_height
        D = np.hypot(r, zz)
        L1 = self.boom
        ext = np.clip(D / self.stretch_margin - (L1 + self.stick), self.lower[3], self.upper[3])
        L2 = self.stick + ext
        cos_e = (D**2 - L1**2 - L2**2) / (2.0 * L1 * L2)
        reach_ok = np.abs(cos_e) <= 1.0
        stick = -np.arccos(np.clip(cos_e, -1.0, 1.0))
        boom = np.arctan2(zz, r) - np.arctan2(L2 * np.sin(stick), L1 + L2 * np.cos(stick))
        yaw = slew if head_yaw is None else np.broadcast_to(np.asarray(head_yaw, float), slew.shape)
        rot = np.mod(yaw - slew + np.pi, 2.0 * np.pi) - np.pi
        q = np.column_stack((slew, boom, stick, ext, rot))
        bad_reach = ~reach_ok
        lo, hi = np.asarray(self.lower), np.asarray(self.upper)
        bad_limit = (q < lo - 1e-9) | (q > hi + 1e-9)
        if np.any(bad_reach) or np.any(bad_limit):
            k = int(np.flatnonzero(bad_reach | bad_limit.any(axis=1))[0])
            where = np.round(P[k], 3).tolist()
            if bad_reach[k]:
                span = (abs(L1 - L2[k]), L1 + L2[k])
                raise UnreachableError(
                    f"head target {where} is out of reach: {D[k]:.2f} m from the boom pivot, "
                    f"the boom and stick span {span[0]:.2f}-{span[1]:.2f} m."
                )
            j = int(np.flatnonzero(bad_limit[k])[0])
            raise UnreachableError(
                f"head target {where} needs {CRANE_JOINTS[j]} = {q[k, j]:.3f}, outside its limits "
                f"[{lo[j]:.3f}, {hi[j]:.3f}]."
            )
        return q[0] if single else q

    def reachable(
        self, head_xyz: ArrayLike, head_yaw: ArrayLike | None = None
    ) -> NDArray[np.bool_]:
        """Boolean mask: which head targets (K, 3) have a solution within the limits."""
        P = np.asarray(head_xyz, dtype=np.float64).reshape(-1, 3)
        out = np.zeros(P.shape[0], dtype=bool)
        for k in range(P.shape[0]):
            try:
                self.inverse(
                    P[k], None if head_yaw is None else np.asarray(head_yaw).reshape(-1)[k]
                )
            except UnreachableError:
                continue
            out[k] = True
        return out

    def max_reach(self) -> float:
        """Largest horizontal head distance from the slew axis at pivot height, metres."""
        return self.pivot_offset + self.stretch_margin * (self.boom + self.stick + self.upper[3])


def compose(*transforms: Sequence[Sequence[float]] | FloatArray) -> FloatArray:
    """Product of 4x4 transforms, left to right."""
    out = np.eye(4)
    for T in transforms:
        out = out @ np.asarray(T, dtype=np.float64)
    return out
