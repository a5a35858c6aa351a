"""Paths for simulated drives, and the pure-pursuit controller that follows them.

:func:`straight_path`, :func:`loop_path` (closed, for loop-closure tests),
:func:`lawnmower_path` and :func:`s_curve_path` (a sine wave, for odometry drift tests) make
waypoints; :func:`clear_corridor` removes the trees the vehicle
would drive through; :func:`_pure_pursuit` turns waypoints into unicycle controls that
:func:`stemmap.sim.trajectory.simulate_run` integrates exactly.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from numpy.typing import ArrayLike

from stemmap.errors import ConfigError, InputError
from stemmap.sim.forest import Stand
from stemmap.types import FloatArray

__all__ = [
    "clear_corridor",
    "distance_to_polyline",
    "lawnmower_path",
    "loop_path",
    "s_curve_path",
    "straight_path",
]

# --------------------------------------------------------------------------------------------
# Paths
# --------------------------------------------------------------------------------------------


def straight_path(start: ArrayLike, end: ArrayLike) -> FloatArray:
    """A straight drive: waypoints (2, 2) from ``start`` to ``end`` (metres)."""
    a = np.asarray(start, dtype=np.float64).reshape(2)
    b = np.asarray(end, dtype=np.float64).reshape(2)
    if np.allclose(a, b):
        raise ConfigError("straight_path needs distinct start and end points.")
    return np.vstack((a, b))


def loop_path(
    center: ArrayLike,
    radii: tuple[float, float],
    *,
    n_points: int = 120,
    laps: float = 1.0,
    start_angle: float = -math.pi / 2,
) -> FloatArray:
    """A closed elliptical loop (counter-clockwise), for loop-closure tests.

    Parameters
    ----------
    center : (2,), metres
    radii : (rx, ry), metres, > 0
    n_points : int
        Waypoints per lap.
    laps : float
        1.0 ends where it started (the loop closes); > 1 revisits the start.
    start_angle : float, radians
        Where on the ellipse the drive starts.

    Returns
    -------
    ndarray of shape (round(n_points * laps) + 1, 2)
    """
    rx, ry = radii
    if not (rx > 0 and ry > 0 and n_points >= 8 and laps > 0):
        raise ConfigError("loop_path needs radii > 0, n_points >= 8 and laps > 0.")
    c = np.asarray(center, dtype=np.float64).reshape(2)
    m = round(n_points * laps)
    a = start_angle + 2 * np.pi * np.arange(m + 1) / n_points
    return c + np.column_stack((rx * np.cos(a), ry * np.sin(a)))


def lawnmower_path(
    bounds: tuple[float, float, float, float],
    spacing: float,
    *,
    margin: float = 2.0,
    turn_points: int = 12,
) -> FloatArray:
    """Back-and-forth strips along x, ``spacing`` apart in y, joined by semicircular turns.

    Parameters
    ----------
    bounds : (xmin, ymin, xmax, ymax), metres
    spacing : float, metres, > 0
        Distance between strips (the turn radius is ``spacing / 2``).
    margin : float, metres
        Distance kept from the bounds.
    turn_points : int
        Waypoints per turn.
    """
    x0, y0, x1, y1 = (float(b) for b in bounds)
    x0, y0, x1, y1 = x0 + margin, y0 + margin, x1 - margin, y1 - margin
    if not (spacing > 0 and x1 - x0 > spacing and y1 - y0 >= 0):
        raise ConfigError(
            f"lawnmower_path: bounds minus margin ({x0}, {y0}, {x1}, {y1}) too small for "
            f"spacing {spacing} m."
        )
    r = spacing / 2
    n_strips = math.floor((y1 - y0) / spacing) + 1
    pts: list[FloatArray] = []
    for i in range(n_strips):
        y = y0 + i * spacing
        left, right = x0 + r, x1 - r
        forward = i % 2 == 0
        xs = (left, right) if forward else (right, left)
        pts.append(np.array([[xs[0], y], [xs[1], y]]))
        if i < n_strips - 1:
            a = np.linspace(-np.pi / 2, np.pi / 2, turn_points + 2)[1:-1]
            cx = right if forward else left
            sign = 1.0 if forward else -1.0
            pts.append(np.column_stack((cx + sign * r * np.cos(a), y + r + r * np.sin(a))))
    return np.vstack(pts)


def s_curve_path(
    size: tuple[float, float],
    *,
    amplitude: float,
    length_scale: float,
    n_points: int,
    margin: float = 5.0,
) -> FloatArray:
    """A sine-wave drive along x across a ``size`` = (width, height) stand, centred in y.

    Waypoints ``x_k`` evenly spaced over ``[margin, width - margin]`` and
    ``y_k = height / 2 + amplitude * sin(x_k / length_scale)``: the heading swings left and
    right (an S per 2 pi ``length_scale`` metres), so odometry tests see both turn directions
    and a drift in yaw shows up as a position error.

    Parameters
    ----------
    size : (width, height), metres
    amplitude : float, metres, 0 <= amplitude < height / 2
    length_scale : float, metres per radian, > 0
    n_points : int, >= 2
    margin : float, metres
        Distance kept from the x bounds.

    Returns
    -------
    ndarray of shape (n_points, 2)
    """
    width, height = (float(v) for v in size)
    if not (
        n_points >= 2
        and length_scale > 0
        and 0 <= amplitude < height / 2
        and width - 2 * margin > 0
    ):
        raise ConfigError(
            f"s_curve_path needs n_points >= 2, length_scale > 0, 0 <= amplitude < height / 2 "
            f"and width > 2 margin; got size {size}, amplitude {amplitude}, length_scale "
            f"{length_scale}, n_points {n_points}, margin {margin}."
        )
    x = np.linspace(margin, width - margin, n_points)
    return np.column_stack((x, height / 2 + amplitude * np.sin(x / length_scale)))


def distance_to_polyline(q: ArrayLike, path: ArrayLike) -> FloatArray:
    """Distance (m) of each point of ``q`` (Q, 2) to the polyline ``path`` (K >= 2, 2)."""
    qq = np.asarray(q, dtype=np.float64).reshape(-1, 2)
    p = np.asarray(path, dtype=np.float64).reshape(-1, 2)
    if qq.shape[0] == 0:
        return np.zeros(0)
    a, b = p[:-1], p[1:]
    ab = b - a
    l2 = np.maximum(np.sum(ab * ab, axis=1), 1e-18)
    t = np.clip(np.einsum("qsk,sk->qs", qq[:, None, :] - a[None], ab) / l2, 0, 1)
    closest = a[None] + t[..., None] * ab[None]
    return np.asarray(np.min(np.linalg.norm(qq[:, None, :] - closest, axis=2), axis=1))


def clear_corridor(stand: Stand, path: ArrayLike, half_width: float) -> Stand:
    """Remove trees whose trunk surface is within ``half_width`` (m) of the path polyline.

    A harvester drives on a strip road: the simulated drive must not pass through trunks.
    Clutter is removed the same way (circles by surface distance, segments by either end or
    midpoint distance).
    """
    p = np.asarray(path, dtype=np.float64).reshape(-1, 2)
    if p.shape[0] < 2:
        raise InputError("clear_corridor needs a path with at least 2 points.")

    def dist_to_path(q: FloatArray) -> FloatArray:
        return distance_to_polyline(q, p)

    keep_trees = dist_to_path(stand.trees_xy) - stand.radii > half_width
    out = stand.subset_trees(keep_trees)
    keep_c = dist_to_path(out.clutter_xy) - out.clutter_radius > half_width
    seg = out.segments
    if seg.shape[0]:
        # distance of a segment to the path: min over 17 points along it (walls are long)
        f = np.linspace(0.0, 1.0, 17)
        pts = seg[:, None, :2] + f[None, :, None] * (seg[:, None, 2:] - seg[:, None, :2])
        d_seg = dist_to_path(pts.reshape(-1, 2)).reshape(seg.shape[0], f.size).min(axis=1)
    else:
        d_seg = np.zeros(0)
    keep_s = (out.segment_owner >= 0) | (d_seg > half_width)
    # non-tree objects whose extent reaches into the corridor are dropped from the truth list
    keep_o = dist_to_path(out.clutter_objects_xy) - out.clutter_objects_extent > half_width
    return replace(
        out,
        clutter_xy=out.clutter_xy[keep_c],
        clutter_radius=out.clutter_radius[keep_c],
        segments=seg[keep_s],
        segment_owner=out.segment_owner[keep_s],
        clutter_objects_xy=out.clutter_objects_xy[keep_o],
        clutter_kinds=tuple(k for k, ok in zip(out.clutter_kinds, keep_o, strict=True) if ok),
        clutter_objects_extent=out.clutter_objects_extent[keep_o],
    )


# --------------------------------------------------------------------------------------------
# Controller
# --------------------------------------------------------------------------------------------


def _resample_polyline(p: FloatArray, ds: float) -> tuple[FloatArray, FloatArray]:
    seg = np.hypot(*np.diff(p, axis=0).T)
    s = np.concatenate(([0.0], np.cumsum(seg)))
    keep = np.concatenate(([True], seg > 1e-12))
    p, s = p[keep], s[keep]
    n = max(math.ceil(s[-1] / ds) + 1, 2)
    sq = np.linspace(0.0, s[-1], n)
    return np.column_stack((np.interp(sq, s, p[:, 0]), np.interp(sq, s, p[:, 1]))), sq


def _pure_pursuit(
    waypoints: FloatArray,
    pose0: FloatArray,
    speed: float,
    dt: float,
    lookahead: float,
    max_yaw_rate: float,
) -> tuple[FloatArray, FloatArray]:
    """Controls (v, w) per step that follow the polyline until its end."""
    ds = min(0.05, lookahead / 10)
    path, s = _resample_polyline(waypoints, ds)
    total = float(s[-1])
    n_look = max(1, round(lookahead / ds))
    window = max(4 * n_look, round(2 * speed * dt / ds) + 4)
    x, y, th = (float(v) for v in pose0)
    idx = 0
    v_out: list[float] = []
    w_out: list[float] = []
    max_steps = int(3 * total / (speed * dt)) + 1000
    for _ in range(max_steps):
        hi = min(idx + window, path.shape[0])
        seg = path[idx:hi]
        idx += int(np.argmin((seg[:, 0] - x) ** 2 + (seg[:, 1] - y) ** 2))
        if total - s[idx] < speed * dt or idx == path.shape[0] - 1:
            break
        tx, ty = path[min(idx + n_look, path.shape[0] - 1)]
        alpha = math.atan2(ty - y, tx - x) - th
        alpha = math.atan2(math.sin(alpha), math.cos(alpha))
        dist = max(math.hypot(tx - x, ty - y), 1e-6)
        w = max(-max_yaw_rate, min(max_yaw_rate, 2.0 * speed * math.sin(alpha) / dist))
        v_out.append(speed)
        w_out.append(w)
        # advance with the exact arc
        dth = w * dt
        half = dth / 2.0
        chord = speed * dt * (math.sin(half) / half if half != 0.0 else 1.0)
        x += chord * math.cos(th + half)
        y += chord * math.sin(th + half)
        th += dth
    else:
        raise ConfigError(
            "the vehicle could not follow the path (too sharp for max_yaw_rate at this speed); "
            "slow down, raise max_yaw_rate, or smooth the waypoints."
        )
    return np.asarray(v_out), np.asarray(w_out)
