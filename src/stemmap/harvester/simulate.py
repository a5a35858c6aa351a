"""Simulated trunk capture: scanner on the boom over a simulated stand, closing the loop.

Each cycle follows Zheng et al. 2012 §5: scan from the scanner's true pose (with boom
vibration), detect trunks, map them into the base frame with the *encoder* joint values (eq. 11),
keep the chosen target by nearest-neighbour association, plan set-points to the capture pose,
execute the first ten with hydraulic tracking error, and repeat until the head is within the
capture tolerance.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from stemmap.errors import StemmapError
from stemmap.harvester.capture import (
    PlannerConfig,
    ScannerMount,
    choose_target,
    plan_capture,
    scanner_pose,
    trunks_to_base,
)
from stemmap.harvester.kinematics import FloatArray, ForestryCrane, UnreachableError
from stemmap.sim.forest import Stand, random_stand
from stemmap.sim.scanner import ScannerModel, simulate_scan
from stemmap.sim.tilted import simulate_tilted_scan
from stemmap.types import LaserScan, Pose2

__all__ = [
    "CaptureNoise",
    "CaptureResult",
    "CycleLog",
    "harvester_stand",
    "simulate_capture",
    "zheng2012_scanner",
]

#: (scan, roll, pitch) -> (centres (K, 2) in the level scanner frame, diameters (K,)); roll and
#: pitch (rad) are the AHRS reading, None without one (Zheng 2012 §2, eq. 1)
TrunkDetector = Callable[[LaserScan, float | None, float | None], tuple[FloatArray, FloatArray]]


def zheng2012_scanner(range_noise: float = 0.01) -> ScannerModel:
    """The SICK LMS291 set-up of Zheng 2012 §2: 0.25 deg resolution, 100 deg field, 8 m range."""
    return ScannerModel(
        angle_min=math.radians(-50.0),
        angle_max=math.radians(50.0),
        angle_increment=math.radians(0.25),
        range_min=0.1,
        range_max=8.0,
        range_noise=range_noise,
    )


def default_detector() -> TrunkDetector:
    """Our default 2D trunk detector (``stemmap.scan.detect``), adapted to the loop's needs."""
    from stemmap.scan.detect import ScanTrunkDetector

    det = ScanTrunkDetector.from_preset("stemmap")

    def detect(
        scan: LaserScan, roll: float | None, pitch: float | None
    ) -> tuple[FloatArray, FloatArray]:
        obs = det.detect(scan, roll=roll, pitch=pitch)
        return np.asarray(obs.centers), np.asarray(obs.diameters)

    return detect


@dataclass(frozen=True)
class CaptureNoise:
    """Error sources of the loop: joint encoders (what the controller believes), hydraulic
    tracking of set-points, and boom vibration moving the scanner (unknown to the controller).
    ``vibration_tilt`` rocks the scan plane about the mount's roll and pitch per scan;
    ``imu_tilt`` is the AHRS error on roll and pitch (0.2 deg: an Xsens MTi-class unit's
    static accuracy is 0.2-0.5 deg). Angles in rad, lengths in m (1-sigma)."""

    encoder_angle: float = math.radians(0.05)
    encoder_length: float = 0.002
    tracking_angle: float = math.radians(0.3)
    tracking_length: float = 0.005
    vibration_yaw: float = math.radians(0.2)
    vibration_xy: float = 0.01
    vibration_tilt: float = 0.0
    imu_tilt: float = math.radians(0.2)


@dataclass(frozen=True)
class CycleLog:
    """One scan-plan-execute cycle."""

    cycle: int
    n_trunks: int
    target_xy: tuple[float, float]
    target_seen: bool
    distance: float
    k: int
    planning_ms: float
    executed: int


@dataclass(frozen=True, eq=False)
class CaptureResult:
    """Outcome of :func:`simulate_capture` (errors are against the TRUE trunk axis)."""

    success: bool
    reason: str
    target_tree: int
    final_error: float
    cycles: int
    log: tuple[CycleLog, ...]
    head_path: FloatArray
    max_velocity_ratio: float
    max_acceleration_ratio: float
    planning_ms: tuple[float, ...] = field(default_factory=tuple)


def harvester_stand(
    n_trees: int = 25, *, radius: float = 11.0, rng: np.random.Generator | int | None = None
) -> Stand:
    """A stand around a parked harvester: trees in a disc around the crane base, none within 2 m."""
    gen = np.random.default_rng(rng)
    size = 2.0 * radius
    stand = random_stand(n_trees + 8, (size, size), dbh_mean=0.25, dbh_std=0.08, min_spacing=1.2,
                         rng=gen)  # fmt: skip
    xy = stand.trees_xy - radius
    r = np.hypot(xy[:, 0], xy[:, 1])
    keep = (r > 2.0) & (r < radius)
    return Stand(xy[keep][:n_trees], stand.diameters[keep][:n_trees])


def _scan_from(
    stand: Stand, crane: ForestryCrane, q: FloatArray, mount: ScannerMount, model: ScannerModel,
    gen: np.random.Generator, noise: CaptureNoise, time_s: float, tilt: tuple[float, float],
) -> LaserScan:  # fmt: skip
    T = scanner_pose(crane, q, mount)
    yaw = math.atan2(T[1, 0], T[0, 0]) + gen.normal(0.0, noise.vibration_yaw)
    x, y = T[:2, 3] + gen.normal(0.0, noise.vibration_xy, 2)
    if tilt == (0.0, 0.0):  # level: the footprint / mixed-pixel scanner model
        scan, _ = simulate_scan(stand, Pose2(x, y, yaw), model, time=time_s, rng=gen)
        return scan
    height = float(T[2, 3])  # the base frame's z = 0 is the ground at the crane
    return simulate_tilted_scan(stand, Pose2(x, y, yaw), tilt[0], tilt[1], model,
                                height=max(height, 0.1), time=time_s, rng=gen)  # fmt: skip


def simulate_capture(
    stand: Stand,
    *,
    crane: ForestryCrane | None = None,
    q0: FloatArray | None = None,
    mount: ScannerMount | None = None,
    scanner: ScannerModel | None = None,
    planner: PlannerConfig | None = None,
    noise: CaptureNoise | None = None,
    detector: TrunkDetector | None = None,
    mode: Literal["nearest", "index", "bearing"] = "nearest",
    index: int | None = None,
    bearing: float | None = None,
    max_cycles: int = 40,
    association_gate: float = 0.5,
    use_imu: bool = True,
    rng: np.random.Generator | int | None = None,
) -> CaptureResult:
    """Run the receding-horizon capture loop on a simulated stand (base frame = world frame).

    ``index`` (with ``mode="index"``) is the row of the operator's pick among the trunks
    detected in the first scan. When the scan plane is tilted (``mount.roll`` / ``pitch``,
    ``noise.vibration_tilt``) every scan is taken with the tilted-scanner model and, with
    ``use_imu``, the detector gets the AHRS roll and pitch (true + ``noise.imu_tilt``) to
    project the scan onto the horizontal (Zheng 2012 §2-3.1); without it the tilted ranges are
    used as if level (trunks read too far and too wide).
    """
    gen = np.random.default_rng(rng)
    # tilt and AHRS draws come from a child stream: a level run draws exactly as before
    tilt_gen = gen.spawn(1)[0]
    crane = crane or ForestryCrane()
    mount = mount or ScannerMount()
    model = scanner or zheng2012_scanner()
    cfg = planner or PlannerConfig()
    nz = noise or CaptureNoise()
    detect = detector or default_detector()
    q_true = (crane.inverse([3.2, 0.0, 2.0]) if q0 is None else np.asarray(q0, float)).copy()
    qdot = np.zeros(5)
    is_len = np.array([False, False, False, True, False])
    enc_sigma = np.where(is_len, nz.encoder_length, nz.encoder_angle)
    trk_sigma = np.where(is_len, nz.tracking_length, nz.tracking_angle)

    head_path = [crane.head_pose(q_true)[:3, 3]]
    log: list[CycleLog] = []
    plan_ms: list[float] = []
    vr = ar = 0.0
    target_xy: FloatArray | None = None
    t = 0.0
    lost = 0
    for cycle in range(max_cycles):
        q_meas = q_true + gen.normal(0.0, enc_sigma)
        tilt = (0.0, 0.0)
        att: tuple[float | None, float | None] = (None, None)
        if mount.roll or mount.pitch or nz.vibration_tilt:
            r_t, p_t = tilt_gen.normal([mount.roll, mount.pitch], nz.vibration_tilt)
            tilt = (float(r_t), float(p_t))
            if use_imu:
                r_m, p_m = tilt_gen.normal(tilt, nz.imu_tilt)
                att = (float(r_m), float(p_m))
        scan = _scan_from(stand, crane, q_true, mount, model, gen, nz, t, tilt)
        centers, diams = detect(scan, *att)
        xy = trunks_to_base(centers, scanner_pose(crane, q_meas, mount))
        seen = False
        if target_xy is None:
            try:
                j = choose_target(xy, diams, crane, grip_height=cfg.grip_height, mode=mode,
                                  index=index, bearing=bearing)  # fmt: skip
            except StemmapError as exc:
                return _result(
                    False, str(exc), -1, math.nan, cycle, log, head_path, vr, ar, plan_ms
                )
            target_xy = xy[j]
            seen = True
        elif xy.shape[0]:
            dist = np.hypot(*(xy - target_xy).T)
            j = int(np.argmin(dist))
            if dist[j] < association_gate:
                target_xy = xy[j]
                seen = True
        lost = 0 if seen else lost + 1
        if lost > 5:
            return _result(False, "target lost for 5 cycles", -1, math.nan, cycle + 1, log,
                           head_path, vr, ar, plan_ms)  # fmt: skip
        assert target_xy is not None
        target = np.array([target_xy[0], target_xy[1], cfg.grip_height])
        head_est = crane.head_pose(q_meas)[:3, 3]
        d_est = float(np.hypot(*(head_est[:2] - target[:2])))
        if d_est <= cfg.capture_tolerance and np.allclose(qdot, 0.0):
            log.append(CycleLog(cycle, int(xy.shape[0]), (float(target[0]), float(target[1])),
                                seen, d_est, 0, 0.0, 0))  # fmt: skip
            break
        try:
            plan = plan_capture(crane, q_meas, target, qdot_now=qdot, config=cfg)
        except UnreachableError as exc:
            return _result(False, str(exc), -1, math.nan, cycle + 1, log, head_path, vr, ar,
                           plan_ms)  # fmt: skip
        plan_ms.append(plan.planning_ms)
        vr, ar = max(vr, plan.max_velocity_ratio), max(ar, plan.max_acceleration_ratio)
        n_exec = min(cfg.execute, plan.k - 1)
        for i in range(1, n_exec + 1):
            head_path.append(crane.head_pose(plan.q[i] + gen.normal(0.0, trk_sigma))[:3, 3])
        # The hydraulic servo holds each joint near its set-point (encoders close the loop).
        q_true = plan.q[n_exec] + gen.normal(0.0, trk_sigma)
        qdot = plan.qdot[n_exec] if n_exec < plan.k - 1 else np.zeros(5)
        t += float(plan.times[n_exec])
        log.append(CycleLog(cycle, int(xy.shape[0]), (float(target[0]), float(target[1])), seen,
                            d_est, plan.k, plan.planning_ms, n_exec))  # fmt: skip
    else:
        return _result(False, f"not captured within {max_cycles} cycles", -1, math.nan,
                       max_cycles, log, head_path, vr, ar, plan_ms)  # fmt: skip

    assert target_xy is not None
    truth = np.hypot(*(stand.trees_xy - target_xy).T)
    tree = int(np.argmin(truth))
    head = crane.head_pose(q_true)[:3, 3]
    err = float(np.hypot(*(head[:2] - stand.trees_xy[tree])))
    ok = err <= 0.15  # Zheng 2012 §4: the accuracy requirement of the harvesting head
    reason = "captured" if ok else f"closed the gripper {err:.3f} m from the trunk axis"
    return _result(ok, reason, tree, err, len(log), log, head_path, vr, ar, plan_ms)


def _result(
    ok: bool, reason: str, tree: int, err: float, cycles: int, log: list[CycleLog],
    head_path: list[FloatArray], vr: float, ar: float, plan_ms: list[float],
) -> CaptureResult:  # fmt: skip
    return CaptureResult(
        success=ok,
        reason=reason,
        target_tree=tree,
        final_error=err,
        cycles=cycles,
        log=tuple(log),
        head_path=np.asarray(head_path),
        max_velocity_ratio=vr,
        max_acceleration_ratio=ar,
        planning_ms=tuple(plan_ms),
    )
