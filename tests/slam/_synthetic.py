"""A small, fast synthetic tree-landmark run with ground truth (shared by SLAM tests)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from stemmap.slam.base import Controls, SlamProblem, TreeFrames, observe
from stemmap.slam.motion import AckermannModel, rollout


def loop_problem(
    seed: int = 0,
    *,
    radius: float = 25.0,
    laps: float = 1.0,
    speed: float = 3.0,
    frame_dt: float = 0.2,
    n_trees: int = 100,
    sigma_r: float = 0.05,
    sigma_b: float = math.radians(0.3),
    speed_scale: float = 1.02,
    steer_bias: float = 0.004,
):
    """Ackermann car (laser offset (3.78, 0.5)) driving ``laps`` circles among random trees.

    Odometry is biased (2 % speed scale, 0.004 rad steering bias) and noisy, so dead reckoning
    drifts by metres; detections have range/bearing noise ``sigma_r``/``sigma_b``.
    Returns (problem, true vehicle poses at frame times, true tree xy, true diameters).
    """
    rng = np.random.default_rng(seed)
    m = AckermannModel(sigma_speed=0.1, sigma_steer=0.01)
    T = laps * 2 * math.pi * radius / speed
    t = np.arange(0.0, T + 1e-9, 0.025)
    alpha = math.atan(m.L / radius)
    v_enc = speed * (1 - math.tan(alpha) * m.H / m.L)
    true_c = Controls(t, np.full(t.size, v_enc), np.full(t.size, alpha), "ackermann")
    meas_c = Controls(
        t,
        v_enc * speed_scale + rng.normal(0, 0.1, t.size),
        alpha + steer_bias + rng.normal(0, 0.01, t.size),
        "ackermann",
    )
    ft = np.arange(0.0, T + 1e-9, frame_dt)
    truth = rollout(m, true_c, ft)
    # trees in an annulus around the circle driven by the laser, with a clear corridor
    ang = rng.uniform(0, 2 * math.pi, n_trees)
    rad = radius + np.where(rng.uniform(size=n_trees) < 0.5, -1, 1) * rng.uniform(3, 18, n_trees)
    trees = np.column_stack((rad * np.cos(ang), radius + rad * np.sin(ang)))
    trees = trees - [0.0, 0.0]
    diam = rng.uniform(0.15, 0.6, n_trees)
    ptr = [0]
    R, B, D = [], [], []
    for f in range(ft.size):
        r, b = observe(truth[f], trees, m.sensor_offset)
        k = (r < 30.0) & (np.abs(b) < math.pi / 2)
        R.append(r[k] + rng.normal(0, sigma_r, k.sum()))
        B.append(b[k] + rng.normal(0, sigma_b, k.sum()))
        D.append(diam[k] + rng.normal(0, 0.03, k.sum()))
        ptr.append(ptr[-1] + int(k.sum()))
    frames = TreeFrames(ft, np.array(ptr), np.concatenate(R), np.concatenate(B), np.concatenate(D))
    problem = SlamProblem(
        meas_c, frames, m, sensor_offset=m.sensor_offset, max_range=30.0, name="synthetic loop"
    )
    return problem, truth, trees, diam


def split_problem(problem: SlamProblem, t_split: float) -> tuple[SlamProblem, SlamProblem]:
    """Two sessions of one run: before and after ``t_split`` (s), each from the origin."""

    def part(t0: float, t1: float) -> SlamProblem:
        return dataclasses.replace(
            problem,
            controls=problem.controls.slice(t0, t1),
            frames=problem.frames.slice(t0, t1),
            initial_pose=(0.0, 0.0, 0.0),
        )

    return part(0.0, t_split), part(t_split, math.inf)
