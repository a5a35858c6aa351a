"""Simulated laser + camera rigs with ground truth.

* :func:`xue2018_rig` -- a 2D laser with a camera above it, tilted down (Xue et al. 2018 §3.1:
  1280 x 720 pixels, ~60 deg field of view, 15 deg down).
* :func:`simulate_plate_views` -- the notched calibration plate (Xue §2.3.4) at random poses:
  true A, B, C, their laser measurements, their pixels, and the plate's laser scan.
* :func:`render_scene` -- one laser scan plus one RGB image of a stand with clutter: trunks as
  textured vertical bands with a known bark colour, bushes (green blobs), walls / posts (grey
  vertical structures that are wide or not bark-coloured), ground and sky; per-pixel truth.

Everything is pure numpy (no OpenGL): an image is a per-column ray cast against circles plus
per-row shading, which is exact for vertical cylinders seen by an upright pinhole camera.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.errors import ConfigError
from stemmap.sim.forest import Stand
from stemmap.sim.scanner import ScannerModel, cast_rays, simulate_scan
from stemmap.types import FloatArray, LaserScan, Pose2
from stemmap.vision.calibrate import XUE2018_PLATE, PlateModel
from stemmap.vision.camera import (
    LASER_TO_CAMERA_AXES,
    CameraModel,
    RigidTransform,
    project_points,
    rotation_about,
)

__all__ = [
    "CameraRig",
    "PlateView",
    "Scene",
    "SceneTruth",
    "render_scene",
    "simulate_plate_views",
    "xue2018_rig",
]


@dataclass(frozen=True, eq=False)
class CameraRig:
    """A camera and its pose relative to the 2D laser (laser plane z = 0)."""

    camera: CameraModel
    laser_to_camera: RigidTransform

    @property
    def camera_position(self) -> FloatArray:
        """Camera centre in the laser frame, metres."""
        return self.laser_to_camera.inverse().t


def xue2018_rig(
    *,
    width: int = 1280,
    height: int = 720,
    hfov_deg: float = 60.0,
    tilt_deg: float = 15.0,
    camera_offset: tuple[float, float, float] = (0.0, 0.0, 0.3),
    yaw_deg: float = 0.0,
) -> CameraRig:
    """Camera above the laser, pitched down by ``tilt_deg`` (Xue et al. 2018, §3.1).

    ``camera_offset`` is the camera centre in the laser frame (x forward, y left, z up), metres.
    """
    cam = CameraModel.from_fov(width, height, hfov_deg)
    R = (
        rotation_about("x", math.radians(tilt_deg))
        @ rotation_about("y", math.radians(yaw_deg))
        @ LASER_TO_CAMERA_AXES
    )
    c = np.asarray(camera_offset, dtype=np.float64)
    return CameraRig(cam, RigidTransform(R, -R @ c))


# ---------------------------------------------------------------------------------------------
# Calibration plate
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class PlateView:
    """One pose of the notched plate.

    Attributes
    ----------
    abc_plate : (3, 2) true A, B, C in plate units
    abc_laser : (3, 2) true A, B, C in the laser frame (z = 0), metres
    abc_uv : (3, 2) their true pixels
    origin, ex, ey : plate origin and unit axes (laser frame, 3D), metres
    scan : LaserScan of the plate alone (notches recessed by ``plate.depth``)
    """

    abc_plate: FloatArray
    abc_laser: FloatArray
    abc_uv: FloatArray
    origin: FloatArray
    ex: FloatArray
    ey: FloatArray
    scan: LaserScan

    def plate_to_laser3d(self, ab: FloatArray, unit: float) -> FloatArray:
        """Plate units (N, 2) -> 3D laser-frame points on the plate face."""
        a = np.asarray(ab, dtype=np.float64).reshape(-1, 2)
        return self.origin + unit * (a[:, :1] * self.ex + a[:, 1:] * self.ey)


def _plate_scan(
    origin: FloatArray,
    ex: FloatArray,
    ey: FloatArray,
    normal: FloatArray,
    plate: PlateModel,
    abc: FloatArray,
    scanner: ScannerModel,
    rng: np.random.Generator,
) -> LaserScan:
    """Ray-cast the plate's cross-section in the laser plane (front face + recessed notches)."""

    def to_xy(a: float, b: float, depth: float) -> FloatArray:
        p = origin + plate.unit * (a * ex + b * ey) + depth * normal
        return p[:2]

    # The laser line in plate coordinates, parametrised by plate x; b(a) on the line.
    (xa, ya), (xb, _), (xc, yc) = abc
    slope = (yc - ya) / (xc - xa)

    def on_line(a: float) -> tuple[float, float]:
        return a, ya + slope * (a - xa)

    xs = [-1.0, xa, xb, xc, xc + plate.rect_width, xc + plate.rect_width + 1.0]
    recess = [0.0, plate.depth, 0.0, plate.depth, 0.0]
    segs = []
    for k in range(5):
        p0 = to_xy(*on_line(xs[k]), recess[k])
        p1 = to_xy(*on_line(xs[k + 1]), recess[k])
        segs.append([*p0, *p1])
    for k in range(1, 5):  # notch walls
        p0 = to_xy(*on_line(xs[k]), 0.0)
        p1 = to_xy(*on_line(xs[k]), plate.depth)
        segs.append([*p0, *p1])
    stand = Stand(np.zeros((0, 2)), np.zeros(0), segments=np.asarray(segs))
    scan, _ = simulate_scan(stand, Pose2(0.0, 0.0, 0.0), scanner, rng=rng)
    return scan


def simulate_plate_views(
    rig: CameraRig,
    n_views: int = 7,
    *,
    plate: PlateModel = XUE2018_PLATE,
    distance: tuple[float, float] = (1.5, 3.5),
    lateral: tuple[float, float] = (-0.8, 0.8),
    yaw_deg: float = 20.0,
    roll_deg: float = 4.0,
    scanner: ScannerModel | None = None,
    rng: np.random.Generator | int | None = None,
) -> list[PlateView]:
    """Random plate poses in front of the rig (Xue §3.1 used 7 poses -> 14 or 21 pairs).

    The plate stands vertically (its face normal horizontal, yawed by up to ``yaw_deg``), rolled
    by up to ``roll_deg`` so the scan line crosses it at a slant (the paper's laser slopes down
    slightly). The plate origin is placed so the laser line crosses the trapezoid at 25-75 % of
    its apex height. Views whose A, B or C fall outside the image are redrawn.
    """
    gen = np.random.default_rng(rng)
    sc = scanner or ScannerModel(angle_increment=math.radians(0.25), range_noise=0.0)
    views: list[PlateView] = []
    tries = 0
    s, c, rx = plate.slope, plate.intercept, plate.rect_x
    while len(views) < n_views:
        tries += 1
        if tries > 100 * n_views:
            raise ConfigError("could not place the plate inside the image; widen the ranges.")
        d = gen.uniform(*distance)
        y = gen.uniform(*lateral)
        psi = math.radians(gen.uniform(-yaw_deg, yaw_deg))
        phi = math.radians(gen.uniform(-roll_deg, roll_deg))
        normal = np.array([math.cos(psi), math.sin(psi), 0.0])  # points away from the sensor
        h = np.array([math.sin(psi), -math.cos(psi), 0.0])  # plate x: to the sensor's right
        up = np.array([0.0, 0.0, 1.0])
        ex = math.cos(phi) * h + math.sin(phi) * up
        ey = -math.sin(phi) * h + math.cos(phi) * up
        # Laser line in plate coords: a sin(phi) + b cos(phi) = k with k = -o_z / unit.
        height = gen.uniform(0.25, 0.75) * (c / 2.0)
        mid_a = 0.7
        k = mid_a * math.sin(phi) + height * math.cos(phi)
        centre = np.array([d, y, 0.0])
        origin = centre - plate.unit * (mid_a * ex + height * ey)
        # origin z must give k: o_z = -unit k (by construction, since centre z = 0).
        sp, cp = math.sin(phi), math.cos(phi)
        xa = k / (sp + s * cp)
        xb = (k - c * cp) / (sp - s * cp)
        yc = (k - rx * sp) / cp
        abc = np.array([[xa, s * xa], [xb, -s * xb + c], [rx, yc]])
        P = origin + plate.unit * (abc[:, :1] * ex + abc[:, 1:] * ey)
        uv, front = project_points(rig.laser_to_camera.apply(P), rig.camera)
        if not (np.all(front) and np.all(rig.camera.in_image(uv))):
            continue
        scan = _plate_scan(origin, ex, ey, normal, plate, abc, sc, gen)
        views.append(PlateView(abc, P[:, :2], uv, origin, ex, ey, scan))
    return views


# ---------------------------------------------------------------------------------------------
# Laser + camera scenes
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class SceneTruth:
    """Ground truth of a rendered scene.

    Attributes
    ----------
    label : (H, W) int32 -- per-pixel object id: tree index >= 0, -2 bush, -3 wall / post,
        -4 ground, -5 sky
    tree_visible : (T,) bool -- trees whose band is visible in the image
    tree_uv_box : (T, 4) int -- x, y, w, h of each tree's visible band (0 where not visible)
    hit_id : (B,) int -- per-beam hit of the laser scan (tree index, -2 clutter, -1 none)
    """

    label: NDArray[np.int32]
    tree_visible: NDArray[np.bool_]
    tree_uv_box: NDArray[np.int64]
    hit_id: NDArray[np.int64]


@dataclass(frozen=True, eq=False)
class Scene:
    """One synchronised laser scan + RGB image (uint8, (H, W, 3)) of a stand, with truth."""

    scan: LaserScan
    image: NDArray[np.uint8]
    rig: CameraRig
    stand: Stand
    pose: Pose2
    truth: SceneTruth
    depth: FloatArray = field(default_factory=lambda: np.zeros((0, 0)))


#: Colours (RGB, 0-255) of the rendered classes. Bark follows Xue's rule (all channels < 200,
#: blue <= green, no channel < 50 on trunks); soil has one channel < 50; foliage is green.
_BARK = np.array([120.0, 100.0, 80.0])
_SOIL = np.array([150.0, 110.0, 40.0])
_BUSH = np.array([60.0, 140.0, 50.0])
_WALL = np.array([185.0, 185.0, 195.0])
_SKY = np.array([210.0, 225.0, 245.0])


def _cast(
    origin: FloatArray, az: FloatArray, xy: FloatArray, r: FloatArray, seg: FloatArray, far: float
) -> tuple[FloatArray, NDArray[np.int64]]:
    """First-hit horizontal distance and object index per azimuth (inf / -1 where none)."""
    n = xy.shape[0]
    st = Stand(
        xy.reshape(-1, 2) if n else np.zeros((0, 2)),
        2.0 * r if n else np.zeros(0),  # Stand takes diameters
        segments=seg,
        segment_owner=np.full(seg.shape[0], -1, dtype=np.int64),
    )
    if n == 0 and seg.shape[0] == 0:
        return np.full(az.shape, np.inf), np.full(az.shape, -1, dtype=np.int64)
    return cast_rays(origin, az, st, far)


def render_scene(
    stand: Stand,
    pose: Pose2,
    rig: CameraRig | None = None,
    *,
    scanner: ScannerModel | None = None,
    laser_height: float = 1.0,
    trunk_height: float = 6.0,
    bush_height: float = 1.6,
    wall_height: float = 2.0,
    post_height: float = 2.5,
    mimic_fraction: float = 0.0,
    mimic_mask: ArrayLike | None = None,
    bark_jitter: float = 20.0,
    pixel_noise: float = 5.0,
    rng: np.random.Generator | int | None = None,
) -> Scene:
    """Render one laser scan and one camera image of ``stand`` seen from ``pose``.

    The laser is at ``pose`` (world frame), ``laser_height`` above flat ground; the camera is
    mounted by ``rig`` (its lens distortion, if any, is rendered). Every pixel's ray is
    intersected exactly with vertical cylinders (trees, clutter circles) and vertical planes
    (segments): the horizontal hit distance comes from a 2D ray cast along the pixel's azimuth
    (azimuths binned at 1/4 pixel), the hit height from the pixel's elevation. Classes:

    * trees: bark-coloured (per-tree jitter), patchy bark texture, Lambertian shading, from
      the ground to ``trunk_height``;
    * clutter circles: green leafy bushes up to ``bush_height``, except a fraction
      ``mimic_fraction`` drawn as bark-coloured posts up to ``post_height`` (distractors a colour
      rule cannot reject; the laser's width evidence can); ``mimic_mask`` (C,) picks them
      explicitly instead;
    * segments: grey walls / fences up to ``wall_height``;
    * soil-coloured ground and sky.

    Returns
    -------
    Scene with per-pixel labels, per-beam hit ids and a z-depth image (metres, NaN for sky).
    """
    gen = np.random.default_rng(rng)
    rig = rig or xue2018_rig()
    cam = rig.camera
    H, W = cam.height, cam.width
    scan, hit = simulate_scan(stand, pose, scanner, rng=gen)

    T_cl = rig.laser_to_camera.inverse()
    c_l = T_cl.t
    uu, vv = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    # Each pixel's ray (z_cam = 1), through the lens model: with distortion coefficients the
    # image is rendered as the real, distorted camera sees it.
    xy_n = cam.normalised(np.column_stack((uu.ravel(), vv.ravel()))).reshape(H, W, 2)
    d_cam = np.concatenate((xy_n, np.ones((H, W, 1))), axis=-1)
    d_l = d_cam @ T_cl.R.T
    horiz = np.hypot(d_l[..., 0], d_l[..., 1])
    az = np.arctan2(d_l[..., 1], d_l[..., 0])
    tan_el = d_l[..., 2] / horiz
    nb = 4 * W
    a0, a1 = float(az.min()), float(az.max())
    bins = np.linspace(a0, a1, nb)
    b_idx = np.clip(np.rint((az - a0) / max(a1 - a0, 1e-12) * (nb - 1)).astype(np.int64), 0, nb - 1)
    cth, sth = math.cos(pose.theta), math.sin(pose.theta)
    o_w = np.array([pose.x + cth * c_l[0] - sth * c_l[1], pose.y + sth * c_l[0] + cth * c_l[1]])
    far = 80.0
    az_w = bins + pose.theta
    u_w = np.column_stack((np.cos(az_w), np.sin(az_w)))
    ground_z = -laser_height
    cz = c_l[2]

    n_t = stand.n_trees
    n_c = stand.clutter_xy.shape[0]
    mimic = np.zeros(n_c, bool)
    if mimic_mask is not None:
        mimic = np.asarray(mimic_mask, dtype=bool).reshape(-1)
        if mimic.shape != (n_c,):
            raise ConfigError(f"mimic_mask needs {n_c} values (one per clutter circle).")
    elif n_c and mimic_fraction > 0:
        mimic[gen.permutation(n_c)[: round(mimic_fraction * n_c)]] = True
    noseg = np.zeros((0, 4))
    r_tree, i_tree = _cast(o_w, az_w, stand.trees_xy, stand.radii, noseg, far)
    r_bush, _ = _cast(o_w, az_w, stand.clutter_xy[~mimic], stand.clutter_radius[~mimic], noseg, far)
    r_post, i_post = _cast(
        o_w, az_w, stand.clutter_xy[mimic], stand.clutter_radius[mimic], noseg, far
    )
    r_wall, _ = _cast(o_w, az_w, np.zeros((0, 2)), np.zeros(0), stand.segments, far)

    # Shading and streak texture per tree-hit bin.
    shade = np.ones(nb)
    kbin = np.zeros(nb, dtype=np.int64)
    post_shade = np.ones(nb)
    # Bark texture: patches of 10 deg around the trunk x 0.25 m in height (plates of bark),
    # so texture edges are short while the silhouette edges run the trunk's full height.
    n_hz = max(1, math.ceil(trunk_height / 0.25))
    tex = gen.normal(0.0, 10.0, (max(n_t, 1), 36, n_hz))
    for r_l, i_l, xy, rad, sh in (
        (r_tree, i_tree, stand.trees_xy, stand.radii, shade),
        (r_post, i_post, stand.clutter_xy[mimic], stand.clutter_radius[mimic], post_shade),
    ):
        fin = np.isfinite(r_l) & (i_l >= 0)
        if not fin.any():
            continue
        p = o_w + r_l[fin, None] * u_w[fin]
        nrm = (p - xy[i_l[fin]]) / rad[i_l[fin], None]
        lam = np.clip(-np.sum(nrm * u_w[fin], axis=1), 0.0, 1.0)
        sh[fin] = 0.7 + 0.3 * lam
        if r_l is r_tree:
            phi = np.arctan2(nrm[:, 1], nrm[:, 0])
            k = ((phi + np.pi) / (2 * np.pi) * 36).astype(np.int64) % 36
            kbin[fin] = k

    tree_rgb = _BARK + gen.normal(0.0, bark_jitter, (max(n_t, 1), 3)) * np.array([1.0, 0.8, 0.6])
    tree_rgb[:, 2] = np.minimum(tree_rgb[:, 2], tree_rgb[:, 1] - 5)
    tree_rgb = np.clip(tree_rgb, 60, 185)
    post_rgb = np.clip(_BARK * 0.9 + gen.normal(0.0, bark_jitter, 3) * 0.5, 60, 185)

    img = np.empty((H, W, 3), dtype=np.float64)
    label = np.full((H, W), -5, dtype=np.int32)
    img[:] = _SKY
    # Ground: rays going down hit z = ground_z at horizontal distance (cz - ground_z) / -tan_el.
    with np.errstate(divide="ignore"):
        r_ground = np.where(tan_el < 0, (cz - ground_z) / -tan_el, np.inf)
    zbuf = np.where(np.isfinite(r_ground), r_ground, np.inf)
    gmask = np.isfinite(r_ground)
    img[gmask] = _SOIL
    label[gmask] = -4

    def paint(r_bins: FloatArray, top: float, lab: NDArray[np.int32], rgb: FloatArray) -> None:
        nonlocal img, label, zbuf
        r = r_bins[b_idx]
        z = cz + r * tan_el
        m = np.isfinite(r) & (z >= ground_z) & (z <= ground_z + top) & (r < zbuf)
        zbuf = np.where(m, r, zbuf)
        img = np.where(m[..., None], rgb, img)
        label = np.where(m, lab, label)

    paint(r_wall, wall_height, np.full((H, W), -3, np.int32), np.broadcast_to(_WALL, (H, W, 3)))
    paint(r_bush, bush_height, np.full((H, W), -2, np.int32), np.broadcast_to(_BUSH, (H, W, 3)))
    post_col = post_rgb[None, :] * post_shade[:, None]
    paint(r_post, post_height, np.full((H, W), -3, np.int32), post_col[b_idx])
    it_px = np.clip(i_tree, 0, max(n_t - 1, 0))[b_idx]
    z_px = cz + np.where(np.isfinite(r_tree[b_idx]), r_tree[b_idx], 0.0) * tan_el
    hz = np.clip(((z_px - ground_z) / 0.25).astype(np.int64), 0, n_hz - 1)
    tcol = (tree_rgb[it_px] + tex[it_px, kbin[b_idx], hz][..., None]) * shade[b_idx][..., None]
    paint(r_tree, trunk_height, i_tree[b_idx].astype(np.int32), tcol)

    img += gen.normal(0.0, pixel_noise, img.shape)
    bush_px = label == -2
    img[bush_px] += gen.normal(0.0, 18.0, (int(bush_px.sum()), 3)) * np.array([0.6, 1.0, 0.6])
    image = np.clip(np.rint(img), 0, 255).astype(np.uint8)

    vis = np.zeros(n_t, bool)
    boxes = np.zeros((n_t, 4), dtype=np.int64)
    if n_t:
        lab_t = label >= 0
        ys, xs = np.nonzero(lab_t)
        ids = label[ys, xs]
        for i in np.unique(ids):
            sel = ids == i
            if sel.sum() < 20:
                continue
            vis[i] = True
            x0, x1, y0, y1 = xs[sel].min(), xs[sel].max(), ys[sel].min(), ys[sel].max()
            boxes[i] = (x0, y0, x1 - x0 + 1, y1 - y0 + 1)
    depth = np.where(np.isfinite(zbuf) & (label != -5), zbuf / horiz, np.nan)
    return Scene(scan, image, rig, stand, pose, SceneTruth(label, vis, boxes, hit), depth)
