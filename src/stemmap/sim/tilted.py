"""A 2D scanner whose scan plane is tilted (roll, pitch), e.g. on a moving crane boom.

Zheng et al. (2012, §2-3.1) mount the scanner on the outer boom of a harvester crane with an
AHRS on top, because the crane tilts the scan plane; eq. 1 then projects the tilted ranges onto
the horizontal. This simulator produces the tilted scan that compensation has to undo: every
beam of the scan plane is rotated by the scanner's attitude, intersected exactly with the
stand's vertical trunks (circles in plan view; an oblique ray meets a vertical cylinder where
its horizontal projection meets the circle) and with flat ground, and the *slant* range along
the beam is reported.
"""

from __future__ import annotations

import math

import numpy as np

from stemmap.errors import ConfigError
from stemmap.scan.preprocess import rotation_rpy
from stemmap.sim.forest import Stand
from stemmap.sim.scanner import ScannerModel, cast_rays, scanner_preset
from stemmap.types import LaserScan, Pose2

__all__ = ["simulate_tilted_scan"]


def simulate_tilted_scan(
    stand: Stand,
    pose: Pose2,
    roll: float,
    pitch: float,
    model: ScannerModel | str | None = None,
    *,
    height: float = 1.3,
    time: float = 0.0,
    rng: np.random.Generator | int | None = None,
) -> LaserScan:
    """One scan from a scanner at ``pose`` (plan view), ``height`` m above flat ground, whose
    scan plane is rotated by ``roll`` and ``pitch`` (radians, the ROS / AHRS z-y-x convention of
    :func:`stemmap.scan.preprocess.rotation_rpy`: a beam ``(cos a, sin a, 0)`` of the scan plane
    points along ``Ry(pitch) Rx(roll) (cos a, sin a, 0)`` in the level sensor frame).

    Parameters
    ----------
    stand : Stand -- vertical trunks (and clutter circles / segments) in plan view
    pose : Pose2 -- scanner position and heading, world frame
    roll, pitch : float, radians, |.| < 60 deg
    model : ScannerModel or preset name (default ``sick_lms``); its beam fan, range window,
        noise and dropout are used. Beams are single exact rays (no footprint / mixed pixels).
    height : float, m -- scanner height above the ground plane
    time : float, s
    rng : Generator or seed

    Returns
    -------
    LaserScan -- slant ranges along the tilted beams (``inf`` = no return), sensor frame.

    Notes
    -----
    A beam with horizontal part ``h`` (``|h| = cos`` of its elevation) meets a vertical trunk at
    horizontal distance ``d`` (2D ray cast along ``h``), i.e. slant range ``d / |h|``; a beam
    pointing down at ``d_z < 0`` meets the ground at ``height / -d_z``. Level (roll = pitch =
    0) this is the plan-view ray cast of :func:`stemmap.sim.scanner.cast_rays` exactly.
    """
    m = scanner_preset(model)
    if not (abs(roll) < math.radians(60) and abs(pitch) < math.radians(60)):
        raise ConfigError(f"roll and pitch must be within +-60 deg, got {roll}, {pitch} rad.")
    if not height > 0:
        raise ConfigError(f"scanner height must be > 0 m, got {height}.")
    gen = np.random.default_rng(rng)
    a = m.angle_min + m.angle_increment * np.arange(m.n_beams)
    R = rotation_rpy(roll, pitch, 0.0)
    d = np.column_stack((np.cos(a), np.sin(a), np.zeros_like(a))) @ R.T
    horiz = np.hypot(d[:, 0], d[:, 1])
    az = pose.theta + np.arctan2(d[:, 1], d[:, 0])
    far = m.range_max * float(horiz.max(initial=1.0)) + 1.0
    dh, _ = cast_rays([pose.x, pose.y], az, stand, far)
    slant = np.where(np.isfinite(dh), dh / np.maximum(horiz, 1e-12), np.inf)
    with np.errstate(divide="ignore"):
        ground = np.where(d[:, 2] < -1e-12, height / -d[:, 2], np.inf)
    r = np.minimum(slant, ground)
    finite = np.isfinite(r)
    r = np.where(finite, r + gen.standard_normal(r.shape) * m.range_sigma(np.where(finite, r, 0)),
                 np.inf)  # fmt: skip
    if m.dropout > 0:
        r[gen.random(r.shape) < m.dropout] = np.inf
    with np.errstate(invalid="ignore"):
        r[~((r > m.range_min) & (r < m.range_max))] = np.inf
    return LaserScan(r, m.angle_min, m.angle_increment, time, m.range_min, m.range_max)
