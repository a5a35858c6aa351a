"""``stemmap map``: do the scans turn the way the odometry turns?

A scanner whose beams run clockwise must say so with a negative ``angle_increment`` (ROS
``sensor_msgs/LaserScan``); a tool that writes them with a positive one hands stemmap a
mirrored scan. A single scan cannot reveal it, but a turning drive can: when the vehicle
turns left by ``d_theta``, a tree's bearing in a correct scan moves right by ``d_theta``, in a
mirrored scan left. A wheel odometry whose yaw rate has the wrong sign disagrees with the scans
in exactly the same way. Read as given, such a log gave a map of 203 trees for the 20 of a
real plot (the FORTLS slice driven in a 3 m loop, docs/reliability.md "Input conventions"),
all with confidence >= 0.5 and no word.

:func:`mirror_evidence` predicts each frame's trees into a later frame turned by 15-90
degrees with the dead-reckoned poses, once with the bearings as given and once mirrored about
the scan's centre line, and counts the trees that land within 0.5 m of one seen there.
Only the map's input layer uses it; the detector and the back-ends are untouched.

With ``--motion lidar`` the motion comes from the scans themselves, and a mirrored log is
consistent with itself: reversing the beams about the centre line reflects every scan, scan
matching is equivariant under that reflection (it returns the reflected path: turns of the
opposite sense, the same forward travel when the centre line is the forward axis), and the
map is the reflected forest, which no test inside the log can tell from a real one. Only a
sensor that measures the rotation on its own can: :func:`turn_sense_warning` compares the
scan matcher's turns with a gyro's (``--imu``) or a camera's (``--motion fused``). The same
disagreement is a gyro whose z axis points down (FRD / NED IMUs: clockwise yaw positive).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from stemmap.types import FloatArray

__all__ = [
    "MirrorEvidence",
    "mirror_evidence",
    "mirror_warning",
    "turn_sense",
    "turn_sense_warning",
]

#: Turn between two compared frames (rad): enough to tell the two senses apart, little
#: enough that the same trees are still in view.
_TURN_MIN = math.radians(15.0)
_TURN_MAX = math.radians(90.0)
#: Longest gap (s) between two compared frames (dead reckoning stays within decimetres).
_GAP_MAX_S = 10.0
#: A predicted tree matches one seen in the later frame within this distance (m).
_MATCH_M = 0.5
#: Frames sampled as the first of a pair (the check costs a few milliseconds).
_MAX_PAIRS = 200


@dataclass(frozen=True)
class MirrorEvidence:
    """Trees of turned frame pairs that the odometry predicts onto a tree of the later frame,
    with the bearings as given and mirrored."""

    pairs: int
    matches: int
    matches_mirrored: int

    @property
    def mirrored(self) -> bool:
        """The mirrored reading explains the turns clearly better (at least 20 matches and
        twice those of the reading as given): a decision only on clear evidence."""
        return self.matches_mirrored >= 20 and self.matches_mirrored >= 2 * self.matches + 10


def _turned_pair(
    heading: FloatArray, times: FloatArray, ok: NDArray[np.bool_], i: int
) -> int | None:
    """The first pose after ``i`` (among ``ok``) turned by 15-90 degrees from it within
    :data:`_GAP_MAX_S` seconds (``heading`` unwrapped), or None."""
    turn = np.abs(heading[i + 1 :] - heading[i])
    later = np.flatnonzero(
        (turn >= _TURN_MIN)
        & (turn <= _TURN_MAX)
        & (times[i + 1 :] - times[i] <= _GAP_MAX_S)
        & ok[i + 1 :]
    )
    return None if later.size == 0 else int(i + 1 + later[0])


def _world(pose: FloatArray, ranges: FloatArray, bearings: FloatArray) -> FloatArray:
    a = pose[2] + bearings
    return np.column_stack((pose[0] + ranges * np.cos(a), pose[1] + ranges * np.sin(a)))


def _matches(a: FloatArray, b: FloatArray) -> int:
    if a.shape[0] == 0 or b.shape[0] == 0:
        return 0
    d = np.hypot(a[:, None, 0] - b[None, :, 0], a[:, None, 1] - b[None, :, 1])
    return int(np.count_nonzero(d.min(axis=1) < _MATCH_M))


def mirror_evidence(problem: Any, centre_bearing: float = 0.0) -> MirrorEvidence:
    """Compare the scans' sense of rotation with the odometry's (module docstring).

    ``problem``: a :class:`stemmap.slam.base.SlamProblem` (frames of range / bearing
    observations, controls, sensor offset). ``centre_bearing``: the scan's centre line
    (``angle_min + (N - 1) * angle_increment / 2``), the axis a reversed beam order mirrors
    about; 0 (the forward axis) for detections without their scan geometry.
    """
    from stemmap.slam.base import dead_reckoning, sensor_poses

    frames = problem.frames
    poses = sensor_poses(dead_reckoning(problem).poses, problem.sensor_offset)
    times = np.asarray(frames.times)
    ptr = np.asarray(frames.ptr)
    heading = np.unwrap(poses[:, 2])
    seen = np.diff(ptr) > 0  # frames with at least one tree
    starts = np.flatnonzero(seen)
    if starts.size > _MAX_PAIRS:
        starts = starts[np.linspace(0, starts.size - 1, _MAX_PAIRS).astype(np.int64)]
    pairs = hits = hits_m = 0
    for i in starts:
        j = _turned_pair(heading, times, seen, int(i))
        if j is None:
            continue
        si, sj = slice(ptr[i], ptr[i + 1]), slice(ptr[j], ptr[j + 1])
        ri, bi = frames.ranges[si], frames.bearings[si]
        rj, bj = frames.ranges[sj], frames.bearings[sj]
        pairs += 1
        hits += _matches(_world(poses[i], ri, bi), _world(poses[j], rj, bj))
        mi, mj = 2.0 * centre_bearing - bi, 2.0 * centre_bearing - bj
        hits_m += _matches(_world(poses[i], ri, mi), _world(poses[j], rj, mj))
    return MirrorEvidence(pairs, hits, hits_m)


def mirror_warning(problem: Any, scans: Any = None) -> str | None:
    """The warning to print when the scans turn against the odometry, else None.

    ``scans``: the log's :class:`~stemmap.types.ScanBatch` (for the centre line), or None.
    """
    centre = 0.0
    if scans is not None:
        centre = float(scans.angle_min + (scans.n_beams - 1) * scans.angle_increment / 2.0)
    ev = mirror_evidence(problem, centre)
    if not ev.mirrored:
        return None
    return (
        f"the scans turn against the odometry: over {ev.pairs} turns of 15-90 degrees the "
        f"odometry puts {ev.matches_mirrored} trees back on a tree seen later when the scans "
        f"are read mirrored, {ev.matches} as given. Either the scanner's beams run clockwise "
        "while angle_increment is positive (write it negative, angle_min at the first beam, "
        "as ROS does), or the odometry's yaw rate has the wrong sign. The map is not usable "
        "as it is."
    )


#: A turn of the scan matcher's path counts for :func:`turn_sense` when the other sensor turned
#: by at least this much over the same interval (rad): below it the sign is noise.
_TURN_OTHER_MIN = math.radians(5.0)


def turn_sense(
    times: FloatArray, heading: FloatArray, ref_times: FloatArray, ref_heading: FloatArray
) -> tuple[int, int]:
    """(turns of the same sense, turns of the opposite sense) of the path ``heading`` at
    ``times`` against ``ref_heading`` at ``ref_times``: up to :data:`_MAX_PAIRS` intervals from
    a pose to the first later one turned by 15-90 degrees within 10 s, where the reference
    turned by at least 5 degrees too (outside its time span nothing is counted)."""
    t = np.asarray(times, dtype=np.float64)
    h = np.unwrap(np.asarray(heading, dtype=np.float64))
    rt = np.asarray(ref_times, dtype=np.float64)
    ok = np.isfinite(rt) & np.isfinite(np.asarray(ref_heading, dtype=np.float64))
    if t.size < 2 or np.count_nonzero(ok) < 2:
        return 0, 0
    rh = np.unwrap(np.asarray(ref_heading, dtype=np.float64)[ok])
    inside = (t >= rt[ok][0]) & (t <= rt[ok][-1])
    r = np.interp(t, rt[ok], rh)
    starts = np.flatnonzero(inside)
    if starts.size > _MAX_PAIRS:
        starts = starts[np.linspace(0, starts.size - 1, _MAX_PAIRS).astype(np.int64)]
    same = opposite = 0
    for i in starts:
        j = _turned_pair(h, t, inside, int(i))
        if j is None:
            continue
        dr = r[j] - r[i]
        if abs(dr) < _TURN_OTHER_MIN:
            continue
        if (dr > 0) == (h[j] - h[i] > 0):
            same += 1
        else:
            opposite += 1
    return same, opposite


def gyro_heading(inertial: Any) -> tuple[FloatArray, FloatArray]:
    """(times, heading) of an :class:`~stemmap.io.imu.InertialLog`'s gyro z integrated from 0
    (trapezoids over the rows with a gyro sample)."""
    t = np.asarray(inertial.times, dtype=np.float64)
    wz = np.asarray(inertial.gyro, dtype=np.float64)[:, 2]
    ok = np.isfinite(wz)
    t, wz = t[ok], wz[ok]
    if t.size < 2:
        return t, np.zeros(t.size)
    steps = 0.5 * (wz[1:] + wz[:-1]) * np.diff(t)
    return t, np.concatenate(([0.0], np.cumsum(steps)))


def turn_sense_warning(lidar_path: Any, ref_times: Any, ref_heading: Any, what: str) -> str | None:
    """The warning to print when the scan matcher's path (a :class:`~stemmap.types.
    Trajectory` from the scans alone) turns against ``what`` (``"the IMU's gyro"``, ``"the
    camera's visual odometry"``) on clear evidence, else None: at least 5 opposite turns and
    four times as many as turns of the same sense (the wheel check's margin of
    :class:`MirrorEvidence`, on turn counts)."""
    same, opposite = turn_sense(
        lidar_path.times, lidar_path.poses[:, 2], np.asarray(ref_times), np.asarray(ref_heading)
    )
    if opposite < 5 or opposite < 4 * same:
        return None
    return (
        f"the scans turn against {what}: over {same + opposite} turns of 15-90 degrees the "
        f"scan matcher turned the other way {opposite} times, the same way {same}. Either the "
        "scanner's beams run clockwise while angle_increment is positive (write it negative, "
        "angle_min at the first beam, as ROS does: the map is then a mirror image), or "
        f"{what} measures clockwise turns as positive (an IMU whose z axis points down, FRD / "
        "NED: negate gyro_z). The path and map are not usable as they are."
    )
