"""Pinhole camera model, rigid transforms and projections (laser plane, 3D points) into images.

Frames: the camera frame has x right, y down, z forward (OpenCV). A sensor-to-camera
:class:`RigidTransform` maps a point X_s in the sensor frame (laser: x forward, y left, z up) to
X_c = R X_s + t. Pixel coordinates (u, v) have u to the right, v down, origin at the top-left
pixel's corner centre (OpenCV convention).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.errors import InputError
from stemmap.types import FloatArray

__all__ = [
    "LASER_TO_CAMERA_AXES",
    "CameraModel",
    "RigidTransform",
    "apply_homography",
    "laser_plane_homography",
    "project_laser_points",
    "project_points",
    "rotation_about",
    "undistort_image",
    "undistort_region",
]

#: Iterative undistortion: OpenCV's default 5 iterations leave ~0.05 px at the corners of a
#: k1 = -0.3 lens; 100 iterations to 1e-14 reproject to 1e-13 px.
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)

#: Rotation taking laser axes (x forward, y left, z up) to camera axes (x right, y down, z fwd).
LASER_TO_CAMERA_AXES: FloatArray = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])


def _as_nx(points: ArrayLike, d: int, name: str) -> FloatArray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim == 1 and p.shape[0] == d:
        p = p.reshape(1, d)
    if p.ndim != 2 or p.shape[1] != d:
        raise InputError(f"{name} must have shape (N, {d}), got {p.shape}.")
    return p


def rotation_about(axis: str, angle: float) -> FloatArray:
    """Right-handed rotation matrix about ``axis`` ("x", "y" or "z") by ``angle`` radians."""
    c, s = math.cos(angle), math.sin(angle)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=np.float64)
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=np.float64)
    if axis == "z":
        return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=np.float64)
    raise InputError(f"rotation axis must be 'x', 'y' or 'z', got {axis!r}.")


@dataclass(frozen=True, eq=False)
class CameraModel:
    """Pinhole camera with optional OpenCV distortion.

    Parameters
    ----------
    K : ndarray of shape (3, 3)
        Intrinsic matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]] in pixels.
    width, height : int, pixels
    dist : ndarray of shape (5,), optional
        OpenCV distortion (k1, k2, p1, p2, k3); zeros = no distortion.
    """

    K: FloatArray
    width: int
    height: int
    dist: FloatArray = field(default_factory=lambda: np.zeros(5))

    def __post_init__(self) -> None:
        K = np.array(self.K, dtype=np.float64)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise InputError(f"K must be a finite (3, 3) matrix with fx, fy > 0, got {K!r}.")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise InputError(f"image size must be positive, got {self.width} x {self.height}.")
        d = np.zeros(5)
        dd = np.asarray(self.dist, dtype=np.float64).reshape(-1)
        d[: min(5, dd.size)] = dd[:5]
        K.setflags(write=False)
        d.setflags(write=False)
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", d)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float) -> CameraModel:
        """Square pixels, principal point at the image centre, horizontal field of view."""
        if not 0.0 < hfov_deg < 180.0:
            raise InputError(f"horizontal field of view must be in (0, 180) deg, got {hfov_deg}.")
        f = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        K = np.array([[f, 0, (width - 1) / 2.0], [0, f, (height - 1) / 2.0], [0, 0, 1]])
        return cls(K, width, height)

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    def pixels_to_metres(self, pixels: ArrayLike, depth: ArrayLike) -> FloatArray:
        """Pinhole pixel-to-metric conversion: size = pixels * depth / fx (Öhman 2007, §3.2)."""
        return np.asarray(pixels, dtype=np.float64) * np.asarray(depth, dtype=np.float64) / self.fx

    @property
    def has_distortion(self) -> bool:
        """True when any distortion coefficient is non-zero."""
        return bool(np.any(self.dist != 0))

    def normalised(self, uv: ArrayLike) -> FloatArray:
        """Pixels -> normalised image coordinates (x/z, y/z) with the lens distortion removed.

        The inverse of :func:`project_points` for points in front of the camera: OpenCV's
        iterative inversion of the Brown-Conrady model (k1, k2, p1, p2, k3), run to
        convergence (100 iterations, 1e-14) rather than OpenCV's default 5. Öhman et al. (2007,
        §3.2) correct the lens distortion of their edge points the same way in spirit (their
        reference: Mallon & Whelan 2004).

        Parameters
        ----------
        uv : ndarray of shape (N, 2), pixels

        Returns
        -------
        ndarray of shape (N, 2)
        """
        p = _as_nx(uv, 2, "uv")
        if not self.has_distortion:
            x = (p[:, 0] - self.cx - self.K[0, 1] * (p[:, 1] - self.cy) / self.fy) / self.fx
            return np.column_stack((x, (p[:, 1] - self.cy) / self.fy))
        out = cv2.undistortPoints(
            p.reshape(-1, 1, 2),
            self.K,
            self.dist,
            R=np.eye(3),
            P=np.eye(3),
            criteria=_UNDISTORT_CRITERIA,
        )
        return np.asarray(out, dtype=np.float64).reshape(-1, 2)

    def undistort_points(self, uv: ArrayLike) -> FloatArray:
        """Pixels of the real (distorted) image -> pixels of the ideal pinhole image, same K."""
        xy = self.normalised(uv)
        u = self.K[0, 0] * xy[:, 0] + self.K[0, 1] * xy[:, 1] + self.cx
        return np.column_stack((u, self.fy * xy[:, 1] + self.cy))

    def in_image(self, uv: ArrayLike) -> NDArray[np.bool_]:
        p = _as_nx(uv, 2, "uv")
        return (
            (p[:, 0] >= 0)
            & (p[:, 0] <= self.width - 1)
            & (p[:, 1] >= 0)
            & (p[:, 1] <= self.height - 1)
        )


@dataclass(frozen=True, eq=False)
class RigidTransform:
    """X_target = R X_source + t (metres)."""

    R: FloatArray
    t: FloatArray

    def __post_init__(self) -> None:
        R = np.array(self.R, dtype=np.float64)
        t = np.array(self.t, dtype=np.float64).reshape(-1)
        if R.shape != (3, 3) or t.shape != (3,):
            raise InputError(f"R must be (3, 3) and t (3,), got {R.shape} and {t.shape}.")
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise InputError("R must be a proper rotation matrix (orthonormal, det = +1).")
        R.setflags(write=False)
        t.setflags(write=False)
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)

    def apply(self, points: ArrayLike) -> FloatArray:
        p = _as_nx(points, 3, "points")
        return p @ self.R.T + self.t

    def inverse(self) -> RigidTransform:
        return RigidTransform(self.R.T, -self.R.T @ self.t)

    def compose(self, other: RigidTransform) -> RigidTransform:
        """``self ∘ other``: apply ``other`` first."""
        return RigidTransform(self.R @ other.R, self.R @ other.t + self.t)

    def matrix(self) -> FloatArray:
        M = np.eye(4)
        M[:3, :3] = self.R
        M[:3, 3] = self.t
        return M

    def rotation_angle_to(self, other: RigidTransform) -> float:
        """Angle (radians) of the rotation between self and other."""
        c = (np.trace(self.R.T @ other.R) - 1.0) / 2.0
        return float(math.acos(max(-1.0, min(1.0, c))))


def project_points(
    points_cam: ArrayLike, camera: CameraModel
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Project 3D points in the camera frame to pixels (pinhole + OpenCV distortion).

    Returns
    -------
    uv : ndarray of shape (N, 2), pixels (NaN for points not in front of the camera)
    in_front : ndarray of bool, shape (N,)
    """
    p = _as_nx(points_cam, 3, "points_cam")
    z = p[:, 2]
    front = z > 1e-9
    zs = np.where(front, z, 1.0)
    x, y = p[:, 0] / zs, p[:, 1] / zs
    if np.any(camera.dist != 0):
        k1, k2, p1, p2, k3 = camera.dist
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2**3
        x, y = (
            x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
            y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y,
        )
    K = camera.K
    u = K[0, 0] * x + K[0, 1] * y + K[0, 2]
    v = K[1, 1] * y + K[1, 2]
    uv = np.column_stack((u, v))
    uv[~front] = np.nan
    return uv, front


def laser_plane_homography(camera: CameraModel, laser_to_camera: RigidTransform) -> FloatArray:
    """The 3x3 map G from laser-plane points (x, y, 1) to pixels (Xue et al. 2018, eq. 3).

    The laser plane is z = 0 in the laser frame, so K [R | t] (x, y, 0, 1)^T = K [r1 r2 t] (x, y,
    1)^T, i.e. G = K [r1 r2 t] (distortion-free camera). Scaled so g11 = 1 when possible, the
    normalisation of Xue eq. 10.
    """
    R, t = laser_to_camera.R, laser_to_camera.t
    G = camera.K @ np.column_stack((R[:, 0], R[:, 1], t))
    return G / G[0, 0] if abs(G[0, 0]) > 1e-12 else G / np.linalg.norm(G)


def apply_homography(G: ArrayLike, xy: ArrayLike) -> FloatArray:
    """Map (N, 2) points through a 3x3 homography; NaN where the third coordinate is 0."""
    H = np.asarray(G, dtype=np.float64)
    if H.shape != (3, 3):
        raise InputError(f"homography must have shape (3, 3), got {H.shape}.")
    p = _as_nx(xy, 2, "xy")
    q = p @ H[:, :2].T + H[:, 2]
    w = q[:, 2]
    ok = np.abs(w) > 1e-12
    out = np.full((p.shape[0], 2), np.nan)
    out[ok] = q[ok, :2] / w[ok, None]
    return out


def project_laser_points(
    xy: ArrayLike, camera: CameraModel, laser_to_camera: RigidTransform
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Project 2D laser points (z = 0 in the laser frame) into the image, with distortion."""
    p = _as_nx(xy, 2, "xy")
    return project_points(laser_to_camera.apply(np.column_stack((p, np.zeros(p.shape[0])))), camera)


def undistort_image(image: ArrayLike, camera: CameraModel) -> NDArray[np.uint8]:
    """The whole image as the ideal pinhole camera with the same K would have seen it.

    ``cv2.undistort`` with the camera matrix kept (no cropping or rescaling); pixels whose
    source lies outside the image are black. Returns the input unchanged (as an array) when the
    camera has no distortion.
    """
    img = np.asarray(image)
    if not camera.has_distortion:
        return img
    return np.asarray(cv2.undistort(img, camera.K, camera.dist, None, camera.K))


def undistort_region(
    image: ArrayLike, camera: CameraModel, box: ArrayLike
) -> tuple[NDArray[np.generic], tuple[int, int, int, int]]:
    """Undistort only the part of ``image`` around ``box`` (cheaper than the whole image).

    Parameters
    ----------
    image : (H, W) or (H, W, 3) -- the real (distorted) image
    camera : CameraModel
    box : (x, y, w, h), pixels of the real image

    Returns
    -------
    patch : the undistorted region, bilinear resampling (edge pixels replicated)
    box_ud : (x, y, w, h) of ``patch`` in the ideal pinhole image's pixels: the bounding
        rectangle of the box's outline after undistortion

    Notes
    -----
    Each patch pixel (u, v) of the ideal image is mapped to the real image by the forward lens
    model (:func:`project_points` of the ray K^-1 (u, v, 1)), so straight vertical trunk edges,
    curved by barrel or pincushion distortion, are straight again in the patch.
    """
    img = np.asarray(image)
    b = np.asarray(box, dtype=np.float64).reshape(-1)
    if b.shape != (4,) or not np.all(np.isfinite(b)) or b[2] <= 0 or b[3] <= 0:
        raise InputError(f"box must be (x, y, w, h) with w, h > 0, got {b}.")
    t = np.linspace(0.0, 1.0, 17)
    x0, y0, x1, y1 = b[0], b[1], b[0] + b[2], b[1] + b[3]
    outline = np.concatenate(
        [
            np.column_stack((x0 + t * (x1 - x0), np.full_like(t, y0))),
            np.column_stack((x0 + t * (x1 - x0), np.full_like(t, y1))),
            np.column_stack((np.full_like(t, x0), y0 + t * (y1 - y0))),
            np.column_stack((np.full_like(t, x1), y0 + t * (y1 - y0))),
        ]
    )
    ud = camera.undistort_points(outline)
    ux0, uy0 = math.floor(float(ud[:, 0].min())), math.floor(float(ud[:, 1].min()))
    ux1, uy1 = math.ceil(float(ud[:, 0].max())), math.ceil(float(ud[:, 1].max()))
    w, h = max(1, ux1 - ux0), max(1, uy1 - uy0)
    uu, vv = np.meshgrid(np.arange(ux0, ux0 + w, dtype=np.float64),
                         np.arange(uy0, uy0 + h, dtype=np.float64))  # fmt: skip
    Kinv = np.linalg.inv(camera.K)
    rays = np.stack((uu.ravel(), vv.ravel(), np.ones(uu.size)), axis=1) @ Kinv.T
    src, _ = project_points(rays, camera)
    mx = src[:, 0].reshape(h, w).astype(np.float32)
    my = src[:, 1].reshape(h, w).astype(np.float32)
    patch = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return np.asarray(patch), (ux0, uy0, w, h)
