"""Textured stereo camera frames of a simulated stand, rendered along a drive, with ground truth.

The visual-lidar tree-trunk paper (visual-lidar §2.4, §3.1) runs stereo visual odometry on a
ZED 2 (110° field of view, 672 x 376 px, 12 cm baseline, 10 fps) next to a 2D lidar. This module
renders what such a camera sees of the *same* stand the 2D scanner simulation
(:mod:`stemmap.sim.scanner`) and the 3D lidar simulation (:mod:`stemmap.sim.lidar`) use:

* geometry: the :class:`~stemmap.sim.lidar.Stand3D` ray caster (exact first hits on stems,
  branches, leaf spheres and the ground plane); :func:`stand3d_from_stand` lifts a 2D
  :class:`~stemmap.sim.forest.Stand` (e.g. :func:`~stemmap.sim.forest.row_stand` orchard rows) to
  vertical trunks with the same positions and diameters, plus leaf crowns and shrubs;
* appearance: procedural textures fixed in the *world* (hashed value noise, so a surface looks
  the same from every frame, which is what feature tracking relies on): furrowed bark in
  (arc length around the stem, height), soil and grass on the ground in (x, y), leaves in 3D,
  and a smooth overcast sky gradient (no corners at infinity). Lambertian shading from a
  fixed sun. Texture octaves finer than ~2 pixels at the hit's distance are faded out (a cheap
  level-of-detail filter: without it distant ground would alias and flicker between frames);
* sensor: a rectified stereo pair (left camera = reference, right camera ``baseline`` to its
  right, identical intrinsics), Gaussian pixel noise independent per image, and the true
  z-depth of the left image.

Decision (issue 16): stereo rather than RGB-D, because the paper's sensor is a stereo camera, its
metric scale then comes from the baseline with the depth error growing with distance squared as
in a real stereo rig, and the visual odometry's triangulation is exercised. The true depth image
is returned as well, so the RGB-D path of :mod:`stemmap.odometry.visual` can be tested on the
same frames.

Camera frame convention (OpenCV): x right, y down, z forward. Vehicle frame: x forward, y left,
z up; the planar vehicle pose (x, y, theta) of :mod:`stemmap.sim.trajectory` on the flat ground
``z = 0``.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.errors import ConfigError, InputError
from stemmap.sim.forest import RngLike, Stand, _place_with_spacing, sample_dbh
from stemmap.sim.lidar import LABEL_BRANCH, LABEL_GROUND, LABEL_SHRUB, Stand3D, cast_rays_3d
from stemmap.types import FloatArray, Trajectory

__all__ = [
    "LABEL_SKY",
    "StereoCamera",
    "StereoFrame",
    "camera_poses",
    "iter_stereo",
    "render_stereo",
    "render_view",
    "stand3d_from_stand",
    "vehicle_to_camera",
    "with_forest_edge",
]

#: Label of pixels that hit nothing within the render range (sky).
LABEL_SKY = -99

#: Rotation taking camera-frame vectors (x right, y down, z forward) to the vehicle frame
#: (x forward, y left, z up).
_R_VEH_CAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


@dataclass(frozen=True)
class StereoCamera:
    """A rectified stereo camera mounted on the vehicle.

    Parameters
    ----------
    width, height : int, pixels
    hfov_deg : float, degrees, in (10, 170)
        Horizontal field of view of each (pinhole, undistorted) image.
    baseline : float, metres, > 0
        Distance from the left to the right optical centre (ZED 2: 0.12 m).
    mount : (x, y, z), metres
        Left camera centre in the vehicle frame (x forward, y left, z up above the ground).
    pitch_deg : float, degrees
        Tilt of the optical axis above the horizontal (positive looks UP: the default 5 deg
        axis is (0.996, 0, +0.087) in the vehicle frame). Until Dec 4 this said "positive looks
        down"; the code has always tilted up, and every rendered drive and number measured on
        one was made with the upward tilt, so the docstring was corrected, not the code.
    pixel_noise : float, grey levels (0-255), >= 0
        1-sigma Gaussian noise added to every channel of every image.
    rate_hz : float, > 0
        Frame rate (the paper's 10 fps).
    """

    width: int = 320
    height: int = 200
    hfov_deg: float = 90.0
    baseline: float = 0.12
    mount: tuple[float, float, float] = (0.3, 0.0, 0.8)
    pitch_deg: float = 5.0
    pixel_noise: float = 2.0
    rate_hz: float = 10.0

    def __post_init__(self) -> None:
        if self.width < 16 or self.height < 16:
            raise ConfigError(
                f"StereoCamera needs at least 16 x 16 pixels, got {self.width} x {self.height}."
            )
        if not 10.0 < self.hfov_deg < 170.0:
            raise ConfigError(f"StereoCamera.hfov_deg must be in (10, 170), got {self.hfov_deg}.")
        if not (self.baseline > 0 and self.rate_hz > 0 and self.pixel_noise >= 0):
            raise ConfigError("StereoCamera needs baseline > 0, rate_hz > 0, pixel_noise >= 0.")

    @property
    def fx(self) -> float:
        """Focal length in pixels (square pixels: ``fy == fx``)."""
        return 0.5 * self.width / math.tan(math.radians(self.hfov_deg) / 2)

    @property
    def K(self) -> FloatArray:  # noqa: N802 (the conventional name of the matrix)
        """3x3 intrinsic matrix of both (rectified) images."""
        f = self.fx
        return np.array(
            [[f, 0.0, (self.width - 1) / 2], [0.0, f, (self.height - 1) / 2], [0.0, 0.0, 1.0]]
        )

    def vehicle_from_camera(self) -> FloatArray:
        """4x4 pose of the left camera in the vehicle frame."""
        p = math.radians(self.pitch_deg)
        # rotation about the camera x axis (right); rx.T @ (0, 0, 1) = (0, -sin p, cos p): the
        # optical axis tilts towards camera -y, which is up (camera y points down)
        rx = np.array(
            [[1.0, 0.0, 0.0], [0.0, math.cos(p), math.sin(p)], [0.0, -math.sin(p), math.cos(p)]]
        )
        T = np.eye(4)
        T[:3, :3] = _R_VEH_CAM @ rx.T
        T[:3, 3] = self.mount
        return T


def vehicle_to_camera(poses: ArrayLike, camera: StereoCamera) -> FloatArray:
    """World poses (N, 4, 4) of the left camera for planar vehicle poses (N, 3) on ``z = 0``."""
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    n = p.shape[0]
    T = np.zeros((n, 4, 4))
    c, s = np.cos(p[:, 2]), np.sin(p[:, 2])
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, -s, s, c
    T[:, 2, 2] = 1.0
    T[:, 3, 3] = 1.0
    T[:, 0, 3], T[:, 1, 3] = p[:, 0], p[:, 1]
    return np.asarray(T @ camera.vehicle_from_camera(), dtype=np.float64)


def camera_poses(trajectory: Trajectory, camera: StereoCamera) -> FloatArray:
    """World poses (N, 4, 4) of the left camera along a vehicle :class:`Trajectory`."""
    return vehicle_to_camera(trajectory.poses, camera)


# --------------------------------------------------------------------------------------------
# Stand
# --------------------------------------------------------------------------------------------


def stand3d_from_stand(
    stand: Stand,
    *,
    height_range: tuple[float, float] = (3.5, 6.0),
    taper: float = 0.004,
    crown_base: float = 1.8,
    crown_spheres: int = 10,
    shrub_spheres: int = 6,
    rng: np.random.Generator | int | None = None,
) -> Stand3D:
    """Lift a 2D :class:`Stand` to a 3D stand the camera can see.

    Trunks are vertical cones at the 2D stand's positions with its diameters at breast height
    (so the 2D scanner and the camera see the same stems; with ``taper`` 4 mm/m the radius at a
    0.3-1 m laser height differs by under 4 mm); each tree gets a leaf crown of
    ``crown_spheres`` spheres from ``crown_base`` up; each 2D clutter circle becomes a shrub of
    ``shrub_spheres`` leaf spheres. Ground: the flat plane ``z = 0`` the 2D simulation assumes.
    Wall segments are not lifted.
    """
    lo, hi = height_range
    if not (crown_base + 0.5 < lo <= hi):
        raise ConfigError(
            f"height_range {height_range} must start above crown_base + 0.5 = {crown_base + 0.5}."
        )
    gen = np.random.default_rng(rng)
    xy = stand.trees_xy
    t = xy.shape[0]
    if t == 0:
        raise InputError("stand3d_from_stand: the stand has no trees.")
    heights = np.asarray(gen.uniform(lo, hi, size=t), dtype=np.float64)
    sph = []
    for i in range(t):
        k = crown_spheres
        if k <= 0:
            break
        z = gen.uniform(crown_base + 0.3, heights[i], k)
        spread = 0.35 + 0.35 * (heights[i] - z) / max(heights[i] - crown_base, 1e-6)
        a = gen.uniform(-np.pi, np.pi, k)
        r = spread * np.sqrt(gen.uniform(0.2, 1.0, k))
        sph.append(
            np.column_stack(
                (xy[i, 0] + r * np.cos(a), xy[i, 1] + r * np.sin(a), z, gen.uniform(0.25, 0.5, k))
            )
        )
    cxy, crad = stand.clutter_xy, stand.clutter_radius
    for j in range(cxy.shape[0]):
        k = shrub_spheres
        a = gen.uniform(-np.pi, np.pi, k)
        r = crad[j] * np.sqrt(gen.uniform(0.0, 1.0, k))
        sph.append(
            np.column_stack(
                (
                    cxy[j, 0] + r * np.cos(a),
                    cxy[j, 1] + r * np.sin(a),
                    gen.uniform(0.2, 0.9, k),
                    np.full(k, max(0.15, 0.6 * crad[j])),
                )
            )
        )
    spheres = np.concatenate(sph) if sph else np.zeros((0, 4))
    return Stand3D(
        xy,
        stand.diameters,
        heights,
        np.zeros((t, 2)),
        np.full(t, taper),
        spheres=spheres,
    )


def with_forest_edge(
    stand: Stand,
    *,
    gap: float = 6.0,
    width: float = 10.0,
    density: float = 0.05,
    min_spacing: float = 1.5,
    dbh_mean: float = 0.30,
    rng: RngLike = None,
) -> Stand:
    """``stand`` surrounded by a band of random forest (an orchard or plot inside woodland).

    Trees are placed at ``density`` per m² with ``min_spacing`` surface gaps in the band from
    ``gap`` to ``gap + width`` metres outside ``stand.bounds``; the stand's own trees, clutter
    and segments are kept (its trees first, so their indices do not change) and the bounds
    grow by ``gap + width``. Gives a camera something to see on headland turns, where a bare
    plane beyond the last row leaves only sky and distant ground.
    """
    if not (gap >= 0 and width > 0 and density > 0):
        raise ConfigError("with_forest_edge needs gap >= 0, width > 0 and density > 0.")
    gen = np.random.default_rng(rng)
    x0, y0, x1, y1 = stand.bounds
    m = gap + width
    lo, hi = np.array([x0 - m, y0 - m]), np.array([x1 + m, y1 + m])
    area = (x1 - x0 + 2 * m) * (y1 - y0 + 2 * m) - (x1 - x0 + 2 * gap) * (y1 - y0 + 2 * gap)
    n = int(density * area)
    cand = gen.uniform(lo, hi, size=(200 * max(n, 1), 2))
    inner = (
        (cand[:, 0] > x0 - gap)
        & (cand[:, 0] < x1 + gap)
        & (cand[:, 1] > y0 - gap)
        & (cand[:, 1] < y1 + gap)
    )
    cand = cand[~inner]
    dbh = sample_dbh(cand.shape[0], mean=dbh_mean, std=0.1, dbh_min=0.1, dbh_max=0.8, rng=gen)
    idx = _place_with_spacing(cand, dbh, min_spacing, n)
    poly = stand.tree_is_polygon
    return replace(
        stand,
        trees_xy=np.concatenate((stand.trees_xy, cand[idx])),
        diameters=np.concatenate((stand.diameters, dbh[idx])),
        tree_is_polygon=np.concatenate((poly, np.zeros(idx.size, bool))) if poly.size else poly,
        bounds=(float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])),
    )


# --------------------------------------------------------------------------------------------
# Procedural textures (world-fixed hashed value noise)
# --------------------------------------------------------------------------------------------


def _hash01(ix: NDArray[np.int64], iy: NDArray[np.int64], iz: NDArray[np.int64]) -> FloatArray:
    """Deterministic pseudo-random values in [0, 1) per integer lattice point."""
    h = (
        ix.astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)
        ^ iy.astype(np.uint64) * np.uint64(0xC2B2AE3D27D4EB4F)
        ^ iz.astype(np.uint64) * np.uint64(0x165667B19E3779F9)
    )
    h ^= h >> np.uint64(29)
    h *= np.uint64(0xBF58476D1CE4E5B9)
    h ^= h >> np.uint64(32)
    return np.asarray((h >> np.uint64(40)).astype(np.float64) / float(1 << 24), dtype=np.float64)


def _value_noise(p: FloatArray) -> FloatArray:
    """Trilinear value noise in [-1, 1] at (N, 3) points (lattice spacing 1), smoothstep-faded."""
    f = np.floor(p)
    i = f.astype(np.int64)
    w = p - f
    w = w * w * (3.0 - 2.0 * w)
    out = np.zeros(p.shape[0])
    for dx in (0, 1):
        wx = w[:, 0] if dx else 1.0 - w[:, 0]
        for dy in (0, 1):
            wy = w[:, 1] if dy else 1.0 - w[:, 1]
            for dz in (0, 1):
                wz = w[:, 2] if dz else 1.0 - w[:, 2]
                out += wx * wy * wz * _hash01(i[:, 0] + dx, i[:, 1] + dy, i[:, 2] + dz)
    return 2.0 * out - 1.0


def _fbm(p: FloatArray, footprint: FloatArray, octaves: int, offset: float) -> FloatArray:
    """Fractal sum of value noise; octave ``o`` has wavelength ``2**-o`` (units of ``p``) and
    amplitude ``0.6**o``, faded out where its wavelength is under ~3 pixel footprints."""
    out = np.zeros(p.shape[0])
    norm = 0.0
    for o in range(octaves):
        freq = 2.0**o
        amp = 0.6**o
        lod = np.clip((1.0 / (freq * np.maximum(footprint, 1e-9)) - 2.0) / 2.0, 0.0, 1.0)
        if not lod.any():
            break
        out += amp * lod * _value_noise(p * freq + offset * (o + 1))
        norm += amp
    return out / max(norm, 1e-9)


_SUN = np.array([0.45, 0.35, 0.82]) / np.linalg.norm([0.45, 0.35, 0.82])


def _shade(
    labels: NDArray[np.int64],
    hits: FloatArray,
    dirs: FloatArray,
    rng_m: FloatArray,
    stand: Stand3D,
    fpx: float,
) -> FloatArray:
    """RGB (N, 3) in 0-255 of the hit points of unit world rays ``dirs``."""
    n = labels.shape[0]
    rgb = np.zeros((n, 3))
    foot = rng_m / fpx  # metres per pixel at the hit
    # sky: a smooth vertical gradient (overcast; no corners at infinity)
    m = labels == LABEL_SKY
    if m.any():
        el = np.clip(dirs[m, 2], -1.0, 1.0)
        rgb[m] = np.array([200.0, 215.0, 235.0]) + np.array([-40.0, -30.0, -5.0]) * el[:, None]
    # ground: soil / grass mixture in (x, y)
    m = labels == LABEL_GROUND
    if m.any():
        p = hits[m]
        cos_i = np.maximum(np.abs(dirs[m, 2]), 0.15)
        f = foot[m] / cos_i
        q = np.column_stack((p[:, 0], p[:, 1], np.zeros(p.shape[0])))
        mix = np.clip(0.5 + 1.2 * _fbm(q / 1.5, f / 1.5, 3, 7.7), 0.0, 1.0)
        detail = _fbm(q / 0.15, f / 0.15, 5, 1.3)
        soil = np.array([125.0, 100.0, 70.0])
        grass = np.array([85.0, 120.0, 55.0])
        col = soil * (1.0 - mix[:, None]) + grass * mix[:, None]
        lam = 0.55 + 0.45 * _SUN[2]
        rgb[m] = col * (lam * np.clip(1.0 + 1.6 * detail, 0.2, 2.0))[:, None]
    # stems: furrowed bark in (arc length, height), per-tree tint
    m = labels >= 0
    if m.any():
        ids = labels[m]
        p = hits[m]
        base = stand.base_xyz[ids]
        axis = stand.axes[ids]
        v = p - base
        s = np.sum(v * axis, axis=1)
        perp = v - s[:, None] * axis
        r = np.maximum(np.linalg.norm(perp, axis=1), 1e-6)
        nrm = perp / r[:, None]
        phi = np.arctan2(nrm[:, 1], nrm[:, 0])
        cos_i = np.maximum(np.abs(np.sum(nrm * dirs[m], axis=1)), 0.15)
        f = foot[m] / cos_i
        q = np.column_stack((phi * r / 0.03, s / 0.2, ids * 13.0))
        furrow = _fbm(q, f / 0.03, 4, 2.9)
        q2 = np.column_stack((phi * r / 0.1, s / 0.1, ids * 7.0 + 0.5))
        plates = _fbm(q2, f / 0.1, 3, 5.3)
        tint = 0.85 + 0.3 * _hash01(ids, ids * 3 + 1, np.zeros_like(ids))
        col = np.array([110.0, 88.0, 68.0]) * tint[:, None]
        lam = 0.45 + 0.55 * np.clip(nrm @ _SUN, 0.0, 1.0)
        rgb[m] = col * (lam * np.clip(1.0 + 1.0 * furrow + 0.8 * plates, 0.2, 2.0))[:, None]
    # branches and leaves: 3D noise
    for lab, col0, wl, gain in (
        (LABEL_BRANCH, np.array([100.0, 80.0, 62.0]), 0.05, 0.8),
        (LABEL_SHRUB, np.array([60.0, 115.0, 45.0]), 0.08, 1.0),
    ):
        m = labels == lab
        if m.any():
            tex = _fbm(hits[m] / wl, foot[m] / wl, 4, 4.4 if lab == LABEL_SHRUB else 6.6)
            rgb[m] = col0 * (0.9 + gain * tex)[:, None]
    return rgb


# --------------------------------------------------------------------------------------------
# Rendering
# --------------------------------------------------------------------------------------------


def render_view(
    stand: Stand3D,
    world_from_camera: ArrayLike,
    camera: StereoCamera,
    *,
    range_max: float = 60.0,
) -> tuple[FloatArray, FloatArray, NDArray[np.int64]]:
    """Render one noise-free pinhole image of ``stand`` from a camera pose.

    Parameters
    ----------
    stand : Stand3D
    world_from_camera : array_like (4, 4)
        Camera pose in the world (OpenCV camera axes: x right, y down, z forward).
    camera : StereoCamera
        Image size and intrinsics (``camera.K``).
    range_max : float, metres
        Hits farther than this are sky.

    Returns
    -------
    rgb : ndarray (H, W, 3), float, 0-255
    depth : ndarray (H, W), metres
        z-depth along the optical axis; NaN for sky.
    label : ndarray (H, W), int
        Tree index >= 0, :data:`~stemmap.sim.lidar.LABEL_GROUND`, ``LABEL_BRANCH``,
        ``LABEL_SHRUB`` or :data:`LABEL_SKY`.
    """
    T = np.asarray(world_from_camera, dtype=np.float64).reshape(4, 4)
    H, W = camera.height, camera.width
    # column-major pixel order: a block of rays covers a few columns, a narrow azimuth interval
    uu, vv = np.meshgrid(
        np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64), indexing="xy"
    )
    pix = np.column_stack((uu.ravel(order="F"), vv.ravel(order="F"), np.ones(H * W)))
    d_cam = np.einsum("nj,ij->ni", pix, np.linalg.inv(camera.K))
    zc = 1.0 / np.linalg.norm(d_cam, axis=1)  # z of the unit ray in the camera frame
    d_cam *= zc[:, None]
    d_w = np.einsum("nj,ij->ni", d_cam, T[:3, :3])
    o = T[:3, 3]
    ranges, labels = cast_rays_3d(stand, o, d_w, range_max=range_max, block=1024)
    labels = np.where(np.isfinite(ranges), labels, LABEL_SKY)
    rr = np.where(np.isfinite(ranges), ranges, 0.0)
    hits = o + rr[:, None] * d_w
    rgb = _shade(labels, hits, d_w, np.where(np.isfinite(ranges), ranges, 1e6), stand, camera.fx)
    depth = np.where(np.isfinite(ranges), ranges * zc, np.nan)
    return (
        rgb.reshape(W, H, 3).transpose(1, 0, 2),
        depth.reshape(W, H).T,
        labels.reshape(W, H).T,
    )


@dataclass(frozen=True, eq=False)
class StereoFrame:
    """One rendered stereo frame with ground truth.

    Attributes
    ----------
    time : float, s
    left, right : ndarray (H, W, 3) uint8
        Rectified RGB images (right camera ``baseline`` to the right of the left one).
    depth : ndarray (H, W) float32, metres
        True z-depth of the left image (NaN = sky): the RGB-D variant of the same frame.
    label : ndarray (H, W) int
        What each left pixel shows (see :func:`render_view`).
    world_from_camera : ndarray (4, 4)
        True pose of the left camera.
    vehicle_pose : ndarray (3,)
        True planar vehicle pose (x, y, theta).
    """

    time: float
    left: NDArray[np.uint8]
    right: NDArray[np.uint8]
    depth: NDArray[np.float32]
    label: NDArray[np.int32]
    world_from_camera: FloatArray
    vehicle_pose: FloatArray
    info: dict[str, Any] = field(default_factory=dict)


def iter_stereo(
    stand: Stand3D,
    trajectory: Trajectory,
    camera: StereoCamera | None = None,
    *,
    range_max: float = 60.0,
    rng: np.random.Generator | int | None = None,
) -> Iterator[StereoFrame]:
    """Render a rectified stereo pair (plus true depth) at every pose of a vehicle trajectory.

    Parameters
    ----------
    stand : Stand3D
        E.g. :func:`stand3d_from_stand` of the stand a :func:`~stemmap.sim.simulate_run` drove
        through, so camera frames and laser scans see the same trees.
    trajectory : Trajectory
        Vehicle poses (world frame, flat ground); one frame per pose, stamped with its time.
        For the paper's 10 fps, sample the drive at ``camera.rate_hz``.
    camera : StereoCamera, optional
    range_max : float, metres
    rng : Generator or int seed
        Pixel noise (independent per image).

    Yields
    ------
    StereoFrame
        One per pose, rendered when requested (a long drive need not fit in memory); ~0.5-1 s
        per 320 x 200 stereo pair for an orchard stand on the loaded 2-core machine.
    """
    cam = camera or StereoCamera()
    gen = np.random.default_rng(rng)
    T_wc = camera_poses(trajectory, cam)
    T_lr = np.eye(4)
    T_lr[0, 3] = cam.baseline
    for k in range(len(trajectory)):
        rgb_l, depth, label = render_view(stand, T_wc[k], cam, range_max=range_max)
        rgb_r, _, _ = render_view(stand, T_wc[k] @ T_lr, cam, range_max=range_max)
        imgs = []
        for rgb in (rgb_l, rgb_r):
            if cam.pixel_noise > 0:
                rgb = rgb + gen.normal(0.0, cam.pixel_noise, rgb.shape)
            imgs.append(np.clip(np.rint(rgb), 0, 255).astype(np.uint8))
        yield (
            StereoFrame(
                float(trajectory.times[k]),
                imgs[0],
                imgs[1],
                depth.astype(np.float32),
                label.astype(np.int32),
                T_wc[k],
                np.array(trajectory.poses[k]),
            )
        )


def render_stereo(
    stand: Stand3D,
    trajectory: Trajectory,
    camera: StereoCamera | None = None,
    *,
    range_max: float = 60.0,
    rng: np.random.Generator | int | None = None,
) -> list[StereoFrame]:
    """All frames of :func:`iter_stereo` as a list."""
    return list(iter_stereo(stand, trajectory, camera, range_max=range_max, rng=rng))
