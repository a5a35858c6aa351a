"""From a detected trunk to crane set-points: target choice, Cartesian planning, receding horizon.

Zheng et al. 2012 §5, steps 1-8: scan, form the trunk pose relative to the scanner, compose it
with the scanner-to-head transform (eq. 11), plan ``k`` Cartesian set-points to the capture pose
(``10 < k < 100`` from the distance) within joint velocity and acceleration limits, execute the
first ten, then re-scan and re-plan until the head is within the capture tolerance.

Decisions (docs/algorithms/harvester.md):

* The straight line is time-scaled by a forward-backward pass over the discretised path (joint
  velocity and acceleration limits mapped onto the path parameter), starting from the velocity the
  crane already has, so replanning every ten set-points does not jerk the crane to a stop.
* The scanner sits on the stick; its scan plane may be tilted (``ScannerMount.roll`` /
  ``pitch``: the machine on a slope, the boom's attitude; plus vibration in the simulator). The
  AHRS of Zheng §2 measures roll and pitch and the detector projects the scan onto the
  horizontal (``stemmap.scan.preprocess``); trunks are taken as vertical.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Literal

import numba
import numpy as np
from numpy.typing import ArrayLike

from stemmap.errors import ConfigError, StemmapError
from stemmap.harvester.kinematics import (
    FloatArray,
    ForestryCrane,
    invert_transform,
    make_transform,
    rot_z,
)

__all__ = [
    "Plan",
    "PlannerConfig",
    "ScannerMount",
    "choose_target",
    "plan_capture",
    "scanner_pose",
    "trunk_in_head_frame",
    "trunks_to_base",
    "warm_up_planner",
]


@dataclass(frozen=True)
class ScannerMount:
    """Where the 2D scanner sits on the crane: ``along`` metres out the stick from the
    boom-stick joint, x axis along the slew direction turned by ``yaw``; the scan plane tilted
    by ``roll`` / ``pitch`` (radians, z-y-x as an AHRS reports them; 0 = level)."""

    along: float = 1.0
    yaw: float = 0.0
    roll: float = 0.0
    pitch: float = 0.0


def scanner_pose(crane: ForestryCrane, q: ArrayLike, mount: ScannerMount) -> FloatArray:
    """T_B^S: the scanner frame in the crane base frame (4x4)."""
    qa = np.asarray(q, dtype=np.float64)
    return make_transform(rot_z(float(qa[0]) + mount.yaw), crane.stick_point(qa, mount.along))


def trunks_to_base(centers_scanner: ArrayLike, T_B_S: ArrayLike) -> FloatArray:
    """Trunk centres (K, 2) in the scanner plane -> horizontal positions (K, 2), base frame."""
    c = np.asarray(centers_scanner, dtype=np.float64).reshape(-1, 2)
    T = np.asarray(T_B_S, dtype=np.float64)
    return c @ T[:2, :2].T + T[:2, 3]


def trunk_in_head_frame(
    center_scanner: ArrayLike, T_B_S: ArrayLike, T_B_H: ArrayLike
) -> FloatArray:
    """Zheng 2012 eq. (11): the trunk pose relative to the harvesting head.

    The paper writes ``T_H^T = T_S^T T_H^S``; with our left-to-right convention (``T_A^B`` maps
    B coordinates to A) the same product is ``T_H^T = (T_B^H)^-1 T_B^S T_S^T``, with ``T_S^T`` the
    trunk frame (axis vertical, origin on the axis in the scan plane) seen by the scanner.
    """
    c = np.asarray(center_scanner, dtype=np.float64).reshape(2)
    T_S_T = make_transform(None, (c[0], c[1], 0.0))
    return invert_transform(T_B_H) @ np.asarray(T_B_S) @ T_S_T


def choose_target(
    trunks_xy: ArrayLike,
    diameters: ArrayLike,
    crane: ForestryCrane,
    *,
    grip_height: float,
    mode: Literal["nearest", "index", "bearing"] = "nearest",
    index: int | None = None,
    bearing: float | None = None,
    max_diameter: float = 0.65,
) -> int:
    """Pick the trunk to capture; returns its row in ``trunks_xy`` (base frame, (K, 2)).

    ``nearest``: the nearest trunk (to the slew axis) that the head can reach and grip
    (diameter <= ``max_diameter``); ``index``: the operator's pick by row; ``bearing``: the
    reachable trunk whose bearing from the slew axis is closest to ``bearing`` (rad).

    Raises
    ------
    StemmapError
        If no trunk qualifies, or the picked one cannot be reached or gripped.
    """
    xy = np.asarray(trunks_xy, dtype=np.float64).reshape(-1, 2)
    d = np.asarray(diameters, dtype=np.float64).reshape(-1)
    if xy.shape[0] == 0:
        raise StemmapError("no trunk detected: nothing to target.")
    targets = np.column_stack((xy, np.full(xy.shape[0], grip_height)))
    ok = crane.reachable(targets) & (d <= max_diameter)
    if mode == "index":
        if index is None or not 0 <= index < xy.shape[0]:
            raise ConfigError(f"trunk index {index} is not one of the {xy.shape[0]} detected.")
        if not ok[index]:
            raise StemmapError(
                f"trunk {index} at {np.round(xy[index], 2).tolist()} (diameter {d[index]:.2f} m) "
                "cannot be reached or gripped."
            )
        return index
    if not np.any(ok):
        raise StemmapError(f"none of the {xy.shape[0]} detected trunks is reachable and grippable.")
    cand = np.flatnonzero(ok)
    if mode == "nearest":
        return int(cand[np.argmin(np.hypot(xy[cand, 0], xy[cand, 1]))])
    if mode == "bearing":
        if bearing is None:
            raise ConfigError("mode='bearing' needs a bearing in radians (bearing=...).")
        diff = np.abs(np.angle(np.exp(1j * (np.arctan2(xy[cand, 1], xy[cand, 0]) - bearing))))
        return int(cand[np.argmin(diff)])
    raise ConfigError(f"unknown target mode {mode!r}; use 'nearest', 'index' or 'bearing'.")


@dataclass(frozen=True)
class PlannerConfig:
    """Set-point planning (Zheng §5, step 4) and the receding horizon (steps 5-8).

    ``step_length`` sets k from the distance: ``k = clip(ceil(dist / step_length) + 1, k_min,
    k_max)`` with the paper's ``10 < k < 100``. ``execute`` set-points run before re-planning
    (paper: ten). ``capture_tolerance`` is the head-to-trunk-axis distance at which the gripper
    closes.
    """

    step_length: float = 0.08
    k_min: int = 11
    k_max: int = 99
    execute: int = 10
    capture_tolerance: float = 0.05
    grip_height: float = 0.7
    max_iterations: int = 8

    def __post_init__(self) -> None:
        if not 10 < self.k_min <= self.k_max < 100:
            raise ConfigError(f"need 10 < k_min <= k_max < 100, got {self.k_min}, {self.k_max}.")
        if not 0 < self.execute <= self.k_min:
            raise ConfigError("execute must be in (0, k_min].")
        if not self.step_length > 0 or not self.capture_tolerance > 0:
            raise ConfigError("step_length and capture_tolerance must be > 0.")


@dataclass(frozen=True, eq=False)
class Plan:
    """Planned set-points: head positions (k, 3), joint values (k, 5), times (k,) from now (s),
    joint velocities (k, 5) at the set-points, and the limit utilisation actually reached."""

    setpoints: FloatArray
    q: FloatArray
    times: FloatArray
    qdot: FloatArray
    max_velocity_ratio: float
    max_acceleration_ratio: float
    planning_ms: float = math.nan
    meta: dict[str, float] = field(default_factory=dict)

    @property
    def k(self) -> int:
        return int(self.setpoints.shape[0])

    @property
    def duration(self) -> float:
        return float(self.times[-1])


def _limit_ratios(
    q: FloatArray, times: FloatArray, vmax: FloatArray, amax: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Per-segment velocity and per-interior-point acceleration utilisation (max over joints)
    from finite differences of the timed joint path."""
    dt = np.maximum(np.diff(times), 1e-12)
    vel = np.diff(q, axis=0) / dt[:, None]
    v_ratio = np.max(np.abs(vel) / vmax, axis=1)
    acc = np.diff(vel, axis=0) / (0.5 * (dt[1:] + dt[:-1]))[:, None]
    a_ratio = np.max(np.abs(acc) / amax, axis=1) if acc.size else np.zeros(0)
    return v_ratio, a_ratio


def _time_scale(
    q: FloatArray, s: FloatArray, sdot0: float, vmax: FloatArray, amax: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Path-speed profile sdot(s_i) within joint velocity and acceleration limits, starting at
    ``sdot0`` and ending at rest. Returns (times, sdot).

    A forward-backward pass bounds the path speed by each joint's velocity limit and the path
    acceleration by its acceleration limit (through dq/ds); the curvature term q'' sdot^2 and the
    discretisation are then handled by capping the speed where the finite-difference check of
    the timed path still exceeds a limit, and repeating (converges in a few passes). The passes
    are sequential in s, so they run compiled (:func:`_time_scale_kernel`): in Python a plan
    needing many passes took up to 25 ms, above the paper's 10 ms control period.
    """
    dq_ds = np.abs(np.gradient(q, s, axis=0))
    v_cap = np.min(vmax / np.maximum(dq_ds, 1e-12), axis=1)  # (k,)
    a_lim = np.min(amax / np.maximum(dq_ds, 1e-12), axis=1)
    times, sd = _time_scale_kernel(
        np.ascontiguousarray(q, dtype=np.float64),
        np.ascontiguousarray(s, dtype=np.float64),
        float(sdot0),
        np.ascontiguousarray(vmax, dtype=np.float64),
        np.ascontiguousarray(amax, dtype=np.float64),
        v_cap,
        a_lim,
    )
    return times, sd


@numba.njit(cache=True)
def _time_scale_kernel(
    q: FloatArray,
    s: FloatArray,
    sdot0: float,
    vmax: FloatArray,
    amax: FloatArray,
    v_cap: FloatArray,
    a_lim: FloatArray,
) -> tuple[FloatArray, FloatArray]:  # pragma: no cover - compiled
    """The iterated forward-backward passes of :func:`_time_scale` (same arithmetic as
    :func:`_limit_ratios` for the finite-difference check)."""
    k, nj = q.shape
    ds = s[1:] - s[:-1]
    sd = v_cap.copy()
    times = np.zeros(k)
    v_ratio = np.zeros(k - 1)
    a_ratio = np.zeros(max(k - 2, 0))
    scale = np.ones(k)
    for _ in range(30):
        sd[:] = v_cap
        sd[0] = min(sdot0, v_cap[0])
        for i in range(k - 1):  # forward: accelerate no faster than allowed
            sd[i + 1] = min(sd[i + 1], math.sqrt(sd[i] ** 2 + 2.0 * a_lim[i] * ds[i]))
        sd[k - 1] = 0.0
        for i in range(k - 2, -1, -1):  # backward: leave room to stop
            sd[i] = min(sd[i], math.sqrt(sd[i + 1] ** 2 + 2.0 * a_lim[i] * ds[i]))
        times[0] = 0.0
        for i in range(k - 1):
            times[i + 1] = times[i] + ds[i] / max(0.5 * (sd[i] + sd[i + 1]), 1e-9)
        # finite-difference utilisation of the timed joint path
        v_max_all = 0.0
        a_max_all = 0.0
        for i in range(k - 1):
            dt = max(times[i + 1] - times[i], 1e-12)
            r = 0.0
            for j in range(nj):
                r = max(r, abs((q[i + 1, j] - q[i, j]) / dt) / vmax[j])
            v_ratio[i] = r
            v_max_all = max(v_max_all, r)
        for i in range(k - 2):
            dt0 = max(times[i + 1] - times[i], 1e-12)
            dt1 = max(times[i + 2] - times[i + 1], 1e-12)
            h = 0.5 * (dt1 + dt0)
            r = 0.0
            for j in range(nj):
                v0 = (q[i + 1, j] - q[i, j]) / dt0
                v1 = (q[i + 2, j] - q[i + 1, j]) / dt1
                r = max(r, abs((v1 - v0) / h) / amax[j])
            a_ratio[i] = r
            a_max_all = max(a_max_all, r)
        if v_max_all <= 1.0 + 1e-3 and a_max_all <= 1.0 + 1e-3:
            break
        scale[:] = 1.0
        for i in range(k - 1):
            inv = 1.0 / max(v_ratio[i], 1.0)
            scale[i] = min(scale[i], inv)
            scale[i + 1] = min(scale[i + 1], inv)
        for i in range(k - 2):  # acceleration at point i involves points i-1, i, i+1
            inv = 1.0 / math.sqrt(max(a_ratio[i], 1.0))
            for shift in range(3):
                scale[i + shift] = min(scale[i + shift], inv)
        for i in range(k):
            cap = sd[i] * scale[i] * 0.999 + (v_cap[i] if sd[i] == 0.0 else 0.0)
            v_cap[i] = min(v_cap[i], cap)
            if scale[i] < 1.0:
                a_lim[i] = a_lim[i] * scale[i] ** 2
    return times, sd.copy()


#: Fraction of the joint velocity / acceleration limits the time scaling plans to.
_LIMIT_MARGIN = 0.998


def warm_up_planner() -> None:
    """Compile (or load from the cache) the planner's kernel now.

    Call once at start-up: otherwise the first plan pays it (~50 ms loading the cached kernel,
    seconds on a machine's very first run), far beyond a 10 ms control period.
    """
    q = np.linspace(0.0, 1.0, 6)[:, None] * np.ones((1, 5))
    _time_scale(q, np.linspace(0.0, 1.0, 6), 0.0, np.ones(5), np.ones(5))


def plan_capture(
    crane: ForestryCrane,
    q_now: ArrayLike,
    target_xyz: ArrayLike,
    *,
    target_yaw: float | None = None,
    qdot_now: ArrayLike | None = None,
    config: PlannerConfig | None = None,
) -> Plan:
    """Plan a straight Cartesian line of set-points from the head's pose to the capture pose.

    Parameters
    ----------
    crane : ForestryCrane
    q_now : (5,) current joint values
    target_xyz : (3,) capture position of the head (trunk axis at grip height), base frame
    target_yaw : head yaw at capture (default: facing away from the slew axis, i.e. the head's
        opening towards the trunk along the approach)
    qdot_now : (5,) current joint velocities (default: at rest)
    config : PlannerConfig

    Returns
    -------
    Plan

    Raises
    ------
    UnreachableError
        If the target or any set-point on the line is outside the workspace or joint limits.
    """
    t0 = time.perf_counter()
    cfg = config or PlannerConfig()
    q0 = np.asarray(q_now, dtype=np.float64).reshape(5)
    p_end = np.asarray(target_xyz, dtype=np.float64).reshape(3)
    T0 = crane.head_pose(q0)
    p0 = T0[:3, 3]
    yaw0 = float(q0[0] + q0[4])
    yaw1 = float(np.arctan2(p_end[1], p_end[0])) if target_yaw is None else float(target_yaw)
    dyaw = math.remainder(yaw1 - yaw0, 2.0 * math.pi)
    dist = float(np.linalg.norm(p_end - p0))
    k = int(np.clip(math.ceil(dist / cfg.step_length) + 1, cfg.k_min, cfg.k_max))
    s = np.linspace(0.0, 1.0, k)
    pts = p0 + s[:, None] * (p_end - p0)
    q = crane.inverse(pts, yaw0 + s * dyaw)
    q[:, 4] = np.unwrap(q[:, 4])
    vmax = np.asarray(crane.max_velocity)
    amax = np.asarray(crane.max_acceleration)
    sdot0 = 0.0
    if qdot_now is not None:
        qd = np.asarray(qdot_now, dtype=np.float64).reshape(5)
        g = (q[1] - q[0]) / (s[1] - s[0])
        w = 1.0 / vmax**2
        denom = float(np.sum(w * g * g))
        sdot0 = max(0.0, float(np.sum(w * g * qd)) / denom) if denom > 0 else 0.0
    # the passes stop within 0.1 % of the limits they are given: give them limits 0.2 % inside
    # the crane's, so the executed plan never exceeds a real limit
    times, sd = _time_scale(q, s, sdot0, vmax * _LIMIT_MARGIN, amax * _LIMIT_MARGIN)
    dq_ds = np.gradient(q, s, axis=0)
    qdot = dq_ds * sd[:, None]
    v_ratio, a_ratio = _limit_ratios(q, times, vmax, amax)
    return Plan(
        setpoints=pts,
        q=q,
        times=times,
        qdot=qdot,
        max_velocity_ratio=float(v_ratio.max(initial=0.0)),
        max_acceleration_ratio=float(a_ratio.max(initial=0.0)),
        planning_ms=(time.perf_counter() - t0) * 1e3,
        meta={"distance": dist, "sdot0": sdot0},
    )
